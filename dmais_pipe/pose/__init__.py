"""Generalized absolute pose (paper, section Absolute Pose Estimation).

Groundwork of issue 3:

- `statistics`: the n-independent statistics H, g, c of eq. objfun3 and the translation map of
  eq. t, accumulated in O(n);
- `generate`: the sympy derivation of the six optimality conditions of eq. EF6 in Cayley
  parameters (`python -m dmais_pipe.pose.generate` writes `_equations.py`);
- `equations`: the runtime side, coefficients of the six polynomials for given statistics.
"""

from __future__ import annotations

from ..errors import DmaisError


class PoseError(DmaisError):
    """Input the generalized pose solver cannot handle (too few, collinear or invalid data)."""


from .statistics import PoseStatistics, pose_statistics  # noqa: E402

__all__ = ["PoseError", "PoseStatistics", "pose_statistics"]
