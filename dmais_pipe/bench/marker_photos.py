"""Sub-pixel refinement on real photographs: OpenCV's chessboard samples (tests/data/chessboard).

There is no ground truth in a real photograph, so the reference is the physics of the scene: the
board is a plane with a regular 9 x 6 grid of corners, seen by one camera through one lens. For
each refiner, a camera model (pinhole + 5-coefficient distortion, cv2.calibrateCamera over all
photographs: ~70 parameters for 540 corners) is fitted to that refiner's own corners, and the
residual of each corner to the model is its error. The reference is thus neither refiner's output
(each is judged by how well a rigid physical model explains its corners), and the residual
includes the model's own imperfection equally for both. Corners are started from
cv2.findChessboardCorners' pixel-level estimates; both refiners start from the same points, and
the comparison uses the corners `refine` accepts (its rejections are counted).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pandas as pd

from .marker_regimes import corner_sub_pix
from ..markers.refine import refine_corners

PATTERN = (9, 6)
PHOTOS = Path(__file__).resolve().parents[2] / "tests" / "data" / "chessboard"
#: The left camera's photographs the suite's published figures come from (one camera model is fitted
#: to all of them, so the right camera's and left12-14, added later for the stereo pair, stay out).
SUITE_PHOTOS = tuple(f"left{k:02d}.jpg" for k in (1, 2, 3, 4, 5, 6, 7, 8, 9, 11))


def board_corners(image: np.ndarray) -> np.ndarray | None:
    """(54, 2) pixel-level inner corners of the 9 x 6 board (findChessboardCorners), or None."""
    found, corners = cv2.findChessboardCorners(image, PATTERN, flags=cv2.CALIB_CB_ADAPTIVE_THRESH)
    return corners.reshape(-1, 2).astype(float) if found else None


def _model_residuals(per_image: list[np.ndarray], keep: list[np.ndarray], size) -> np.ndarray:
    """Distances (m,) of the kept corners to a camera model fitted to them (cv2.calibrateCamera)."""
    grid = np.zeros((PATTERN[0] * PATTERN[1], 3), np.float32)
    grid[:, :2] = np.mgrid[0:PATTERN[0], 0:PATTERN[1]].T.reshape(-1, 2)
    objects = [grid[k] for k in keep]
    points = [uv[k].astype(np.float32) for uv, k in zip(per_image, keep)]
    _, K, dist, rvecs, tvecs = cv2.calibrateCamera(objects, points, size, None, None)
    out = []
    for obj, uv, r, t in zip(objects, points, rvecs, tvecs):
        projected, _ = cv2.projectPoints(obj, r, t, K, dist)
        out.append(np.linalg.norm(projected.reshape(-1, 2) - uv, axis=1))
    return np.concatenate(out)


def bench_photos(folder: Path = PHOTOS, names=SUITE_PHOTOS) -> pd.DataFrame:
    """One row per refiner: corners, rejected, median / 95th percentile / RMS residual (px) to the
    camera model fitted to its corners, and the median distance to our corners."""
    ours, theirs = {"refine": []}, {5: [], 11: []}
    keep, size = [], None
    for path in (Path(folder) / name for name in names):
        image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
        start = board_corners(image)
        if start is None:
            continue
        size = image.shape[::-1]
        corners = refine_corners(image, start)
        ours["refine"].append(corners.uv)
        keep.append(np.nonzero(np.all(np.isfinite(corners.uv), axis=1))[0])
        for half in theirs:
            theirs[half].append(corner_sub_pix(image, start, half))
    results = {"refine": ours["refine"], **{f"cornerSubPix win {2 * h + 1}": v for h, v in theirs.items()}}
    reference = np.concatenate([uv[k] for uv, k in zip(ours["refine"], keep)])
    rows = []
    for name, per_image in results.items():
        residual = _model_residuals(per_image, keep, size)
        ours_here = np.concatenate([uv[k] for uv, k in zip(per_image, keep)])
        rows.append({"method": name, "photos": len(keep), "corners": len(residual),
                     "rejected": sum(len(uv) for uv in per_image) - len(residual) if name == "refine" else 0,
                     "median_px": float(np.median(residual)), "p95_px": float(np.percentile(residual, 95)),
                     "rms_px": float(np.sqrt(np.mean(residual**2))),
                     "median_to_refine_px": float(np.median(np.linalg.norm(ours_here - reference, axis=1)))})
    return pd.DataFrame(rows)
