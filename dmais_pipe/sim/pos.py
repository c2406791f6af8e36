"""The POS trajectory the simulator writes for a geodetic world (`geodetic.trajectory`: sbet or csv).

Each flight group is flown at its own time: group g's frame k at TIME_BASE_S + GROUP_SPACING_S g +
FRAME_SPACING_S k + FRAME_OFFSET_S (a time between two samples, so that reading it back interpolates).
The trajectory is sampled at SAMPLE_HZ from a second before a group's first frame to a second after
its last: positions on the natural cubic spline through the frames' POS positions (WGS 84
geocentric), attitudes by slerp between the frames' INS attitudes, held at the frame's own over the
two samples around each frame (so that the frame's attitude is its INS's exactly); a wander angle
that turns slowly, as an Applanix SBET's does.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation, Slerp

from ..geo import ecef_from_geodetic, geodetic_from_ecef
from ..trajectory import sbet_bytes

TIME_BASE_S = 388800.0
GROUP_SPACING_S = 600.0
FRAME_SPACING_S = 2.0
SAMPLE_HZ = 200.0
FRAME_OFFSET_S = 0.42 / SAMPLE_HZ


def frame_times(groups) -> np.ndarray:
    """(F,) the time of each frame of `groups` (F,) (the frames in flight order, groups contiguous)."""
    groups = pd.Series(np.asarray(groups, dtype=object))
    index = pd.factorize(groups)[0]
    within = groups.groupby(index).cumcount().to_numpy()
    return TIME_BASE_S + GROUP_SPACING_S * index + FRAME_SPACING_S * within + FRAME_OFFSET_S


def samples(times: np.ndarray, groups, geodetic: np.ndarray, ned_from_imu: np.ndarray):
    """The trajectory's time (n,), geodetic (n, 3) and heading, pitch, roll (n, 3) deg of frames at
    times (F,) in `groups` (F,) with POS positions geodetic (F, 3) and INS attitudes ned_from_imu
    (F, 3, 3) (module docstring)."""
    groups = np.asarray(groups, dtype=object)
    parts = []
    for group in pd.unique(groups):
        rows = np.flatnonzero(groups == group)
        t = times[rows]
        first = np.floor((t[0] - 1.0) * SAMPLE_HZ) / SAMPLE_HZ
        grid = first + np.arange(int(round((t[-1] + 1.0 - first) * SAMPLE_HZ)) + 1) / SAMPLE_HZ
        ecef = ecef_from_geodetic(geodetic[rows])
        positions = CubicSpline(t, ecef, bc_type="natural")(grid) if len(rows) > 1 else np.repeat(ecef, len(grid), 0)
        rotations = Rotation.from_matrix(ned_from_imu[rows])
        attitude = (Slerp(t, rotations)(np.clip(grid, t[0], t[-1])) if len(rows) > 1
                    else Rotation.from_matrix(np.repeat(ned_from_imu[rows], len(grid), 0))).as_matrix()
        around = np.searchsorted(grid, t)
        for k, j in enumerate(around):  # the samples on either side of each frame: its own attitude
            attitude[j - 1:j + 1] = ned_from_imu[rows[k]]
        parts.append((grid, geodetic_from_ecef(positions), attitude))
    time = np.concatenate([p[0] for p in parts])
    angles = Rotation.from_matrix(np.concatenate([p[2] for p in parts])).as_euler("ZYX", degrees=True)
    return time, np.concatenate([p[1] for p in parts]), angles


def trajectory_file(kind: str, time: np.ndarray, geodetic: np.ndarray, attitude: np.ndarray) -> bytes:
    """The trajectory as an SBET (wander angle 20 deg + 0.01 deg/s) or CSV file's bytes."""
    if kind == "sbet":
        return sbet_bytes(time, geodetic, attitude, 20.0 + 0.01 * (time - time[0]))
    table = pd.DataFrame({"time": time, "lat": geodetic[:, 0], "lon": geodetic[:, 1], "h": geodetic[:, 2],
                          "roll": attitude[:, 2], "pitch": attitude[:, 1], "heading": attitude[:, 0] % 360.0})
    return table.to_csv(index=False, float_format="%.17g").encode()
