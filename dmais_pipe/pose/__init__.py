"""Absolute pose of the rig as a generalized camera (paper, section Absolute Pose Estimation).

The public solvers:

- `solve_generalized_pose(origins, directions, points)`: the paper's globally optimal solver of
  eq. objfun (t eliminated by eq. t, the optimality conditions eq. EF6 in Cayley parameters solved
  by an action-matrix template), with a Lagrangian dual certificate of global optimality;
- `solve_batch(problems, workers=N)`: many frames, in threads (the compiled core runs without the GIL);
- `solve_robust(origins, directions, points, threshold_rad)`: LO-RANSAC over gP3P samples, then
  the global solver on the inliers.

The modules: `statistics` (the O(n) statistics of eq. objfun3), `generate` -> `_equations.py` (the
sympy derivation of eq. EF6), `template` -> `_template.json` (the elimination template),
`_kernels.pyx` (the compiled core), `_refine.pyx` (refinement, MSAC scoring and gP3P compiled;
`_small.pxd` holds the small matrix helpers both cimport), `solver` (the API), `gp3p` (minimal
solver), `refine` (Levenberg-Marquardt on angular residuals, Cramer-Rao bound), `fallback` (the
global search where the certificate fails or most points are behind), `robust`, `build_cpu` (the CPU
the cores were built for) and `flight` (every flight frame of a dataset, for the pose stage
`stages.pose`). Its benchmark is `bench.pose` (`dmais bench pose`).
"""

from __future__ import annotations

from ..errors import PoseError
from .build_cpu import check_cpu

check_cpu()  # before the compiled cores load: instructions this CPU lacks would kill the process

from .statistics import PoseStatistics, pose_statistics
from .robust import solve_robust
from .solver import solve_batch, solve_generalized_pose

__all__ = ["PoseError", "PoseStatistics", "pose_statistics", "solve_batch", "solve_generalized_pose", "solve_robust"]
