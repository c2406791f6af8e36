"""Calibration: PnPf, intrinsic calibration (paper section "Intrinsic Calibration"), later extrinsics.

- `pnpf.solve_pnpf`: pose + focal length with known principal point (initializes the intrinsics);
- `intrinsics.calibrate_camera` / `intrinsics.run_intrinsics`: the paper's procedure per camera,
  eps_calib / eps_eval, and the OpenCV and DLT+LM baselines of tab:intrinsics.
"""

from .intrinsics import IntrinsicsResult, calibrate_camera, run_intrinsics
from .pnpf import solve_pnpf

__all__ = ["IntrinsicsResult", "calibrate_camera", "run_intrinsics", "solve_pnpf"]
