"""Calibration (paper, sections "Intrinsic Calibration" and "Extrinsic Calibration"), on arrays.

- `pnpf.solve_pnpf`: pose + focal length with known principal point (initializes the intrinsics);
- `intrinsics.calibrate_camera`: the paper's procedure per camera, eps_calib / eps_eval, and the
  OpenCV and DLT+LM baselines of tab:intrinsics;
- `extrinsics.calibrate_extrinsics`: the rig from the placements (`localize`, `rig_ba`).
"""

from .intrinsics import IntrinsicsResult, calibrate_camera
from .pnpf import solve_pnpf

__all__ = ["IntrinsicsResult", "calibrate_camera", "solve_pnpf"]
