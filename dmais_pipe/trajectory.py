"""A POS trajectory (Applanix SBET or CSV), and each flight frame's position and INS attitude
interpolated from it at the frame's time.

Formats (docs/dataset.md, "Trajectories"):

- `sbet`: records of 17 little-endian doubles: time (s), latitude, longitude (rad), ellipsoidal
  height (m), three velocities (m/s), roll, pitch, platform heading, wander angle (rad), three
  accelerations, three angular rates. True heading = platform heading - wander angle.
- `csv`: columns time (s), lat, lon (deg), h (m), roll, pitch, heading (deg, true heading); other
  columns ignored.

Positions are WGS 84 latitude, longitude and ellipsoidal height (EPSG:4979); roll, pitch and heading
the INS's NED attitude: ned_from_imu = Rz(heading) Ry(pitch) Rx(roll). Interpolation (`at_times`):
the position in WGS 84 geocentric coordinates (pyproj) by the cubic through the two samples before
and the two after the time where those four exist without a gap, else linearly between the two
around it; the attitude by slerp between those two. A time outside the samples' span, or between
two samples more than MAX_GAP_SAMPLES nominal intervals (the median one) apart, is refused.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .geo import ecef_from_geodetic
from .geometry import exp_so3, log_so3, rotation_from_euler_zyx

#: The doubles of one SBET record.
SBET_DOUBLES = 17
SBET_RECORD_BYTES = 8 * SBET_DOUBLES
CSV_COLUMNS = ("time", "lat", "lon", "h", "roll", "pitch", "heading")
FORMATS = ("sbet", "csv")
#: A frame between two samples further apart than this many nominal (median) intervals is refused.
MAX_GAP_SAMPLES = 5.0


class TrajectoryError(ValueError):
    """A trajectory that cannot be read (`record`: the 1-based SBET record or CSV line at fault), or
    a time it cannot give (`index`: the time's position in the times asked)."""

    def __init__(self, message: str, record: int | None = None, index: int | None = None):
        self.record, self.index = record, index
        super().__init__(message)


@dataclass(frozen=True)
class Trajectory:
    """time (n,) s, increasing; geodetic (n, 3) latitude, longitude (deg), height (m); attitude
    (n, 3) heading, pitch, roll (deg) of ned_from_imu; records (n,) each sample's record (SBET,
    1-based) or line (CSV)."""

    time: np.ndarray
    geodetic: np.ndarray
    attitude: np.ndarray
    records: np.ndarray


def sbet_from_bytes(data: bytes) -> Trajectory:
    """The samples of an SBET file's bytes; TrajectoryError when it ends mid-record or its times do
    not increase."""
    complete, extra = divmod(len(data), SBET_RECORD_BYTES)
    if extra:
        raise TrajectoryError(f"ends mid-record: record {complete + 1} has {extra} of its {SBET_RECORD_BYTES} "
                              "bytes (an SBET record is 17 little-endian doubles)", complete + 1)
    values = np.frombuffer(data, dtype="<f8").reshape(complete, SBET_DOUBLES)
    heading = values[:, 9] - values[:, 10]  # platform heading - wander angle
    trajectory = Trajectory(time=values[:, 0].copy(),
                            geodetic=np.column_stack([np.degrees(values[:, 1:3]), values[:, 3]]),
                            attitude=np.degrees(np.column_stack([heading, values[:, 8], values[:, 7]])),
                            records=np.arange(1, complete + 1))
    check_samples(trajectory, "record")
    return trajectory


def sbet_bytes(time, geodetic, attitude, wander_deg=None) -> bytes:
    """SBET bytes of samples time (n,), geodetic (n, 3), attitude (n, 3) heading, pitch, roll (deg),
    with the platform heading heading + wander (wander_deg (n,), default 0); velocities,
    accelerations and rates 0."""
    n = len(time)
    wander = np.zeros(n) if wander_deg is None else np.asarray(wander_deg, dtype=float)
    values = np.zeros((n, SBET_DOUBLES))
    values[:, 0] = time
    values[:, 1:3] = np.radians(np.asarray(geodetic)[:, :2])
    values[:, 3] = np.asarray(geodetic)[:, 2]
    attitude = np.radians(np.asarray(attitude, dtype=float))
    values[:, 7], values[:, 8] = attitude[:, 2], attitude[:, 1]
    values[:, 9], values[:, 10] = attitude[:, 0] + np.radians(wander), np.radians(wander)
    return values.astype("<f8").tobytes()


def check_samples(trajectory: Trajectory, what: str) -> None:
    """Finite values and strictly increasing times, else TrajectoryError naming the `what` (record,
    line) at fault."""
    values = np.column_stack([trajectory.time, trajectory.geodetic, trajectory.attitude])
    bad = ~np.isfinite(values).all(axis=1)
    if bad.any():
        k = int(np.argmax(bad))
        raise TrajectoryError(f"{what} {trajectory.records[k]}: a value is not a finite number", int(trajectory.records[k]))
    back = np.flatnonzero(np.diff(trajectory.time) <= 0)
    if len(back):
        k = int(back[0]) + 1
        raise TrajectoryError(f"{what} {trajectory.records[k]}: time {trajectory.time[k]:.12g} is not after the "
                              f"previous {what}'s {trajectory.time[k - 1]:.12g}; times must increase",
                              int(trajectory.records[k]))
    if len(trajectory.time) < 2:
        raise TrajectoryError(f"has {len(trajectory.time)} sample(s); a trajectory needs at least 2")


def at_times(trajectory: Trajectory, times) -> tuple[np.ndarray, np.ndarray]:
    """Geocentric positions (m, 3) and ned_from_imu rotations (m, 3, 3) at times (m,) (module
    docstring); TrajectoryError naming the time's index when it is outside the span or in a gap."""
    t, times = trajectory.time, np.asarray(times, dtype=float)
    interval = float(np.median(np.diff(t)))
    left = np.searchsorted(t, times, side="right") - 1  # the sample at or before each time
    for k in range(len(times)):
        if not np.isfinite(times[k]) or times[k] < t[0] or times[k] > t[-1]:
            raise TrajectoryError(f"time {times[k]:.12g} is outside the trajectory's span [{t[0]:.12g}, {t[-1]:.12g}]",
                                  index=k)
    left = np.clip(left, 0, len(t) - 2)
    gap = t[left + 1] - t[left]
    for k in np.flatnonzero(gap > MAX_GAP_SAMPLES * interval):
        raise TrajectoryError(f"time {times[k]:.12g} falls in a gap of {gap[k]:.6g} s between samples {left[k] + 1} and "
                              f"{left[k] + 2} of the trajectory, more than {MAX_GAP_SAMPLES:g} x its {interval:.6g} s "
                              "interval", index=int(k))
    ecef = ecef_from_geodetic(trajectory.geodetic)
    return _positions(t, ecef, times, left, interval), _attitudes(trajectory, times, left)


def _positions(t: np.ndarray, ecef: np.ndarray, times: np.ndarray, left: np.ndarray, interval: float) -> np.ndarray:
    """(m, 3): the cubic through samples left - 1 ... left + 2 where they exist without a gap, else
    the line through left and left + 1."""
    s = (times - t[left]) / (t[left + 1] - t[left])
    out = ecef[left] + s[:, None] * (ecef[left + 1] - ecef[left])
    cubic = (left >= 1) & (left + 2 < len(t))
    rows = np.flatnonzero(cubic)
    if len(rows):
        nodes = left[rows, None] + np.arange(-1, 3)
        spans = np.diff(t[nodes], axis=1)
        rows = rows[(spans <= MAX_GAP_SAMPLES * interval).all(axis=1)]
        nodes = left[rows, None] + np.arange(-1, 3)
        tn, x = t[nodes], times[rows, None]
        weights = np.ones((len(rows), 4))
        for j in range(4):
            for k in range(4):
                if k != j:
                    weights[:, j] *= (x[:, 0] - tn[:, k]) / (tn[:, j] - tn[:, k])
        out[rows] = np.einsum("rj,rjc->rc", weights, ecef[nodes])
    return out


def _attitudes(trajectory: Trajectory, times: np.ndarray, left: np.ndarray) -> np.ndarray:
    """(m, 3, 3) ned_from_imu by slerp between samples left and left + 1."""
    t = trajectory.time
    R = rotation_from_euler_zyx(np.radians(trajectory.attitude))
    s = (times - t[left]) / (t[left + 1] - t[left])
    step = log_so3(np.swapaxes(R[left], 1, 2) @ R[left + 1])
    return R[left] @ exp_so3(s[:, None] * step)


def read_trajectory(path: Path, kind: str, read_csv_table) -> Trajectory:
    """The trajectory file `path` of format `kind` (FORMATS); read_csv_table(path, columns) -> the
    dataset's Table of a CSV file (its reader, with line numbers)."""
    if kind == "sbet":
        return sbet_from_bytes(Path(path).read_bytes())
    table = read_csv_table(path, CSV_COLUMNS)
    values = {column: table.floats(column) for column in CSV_COLUMNS}
    trajectory = Trajectory(time=values["time"], geodetic=np.column_stack([values["lat"], values["lon"], values["h"]]),
                            attitude=np.column_stack([values["heading"], values["pitch"], values["roll"]]),
                            records=np.asarray(table.lines))
    check_samples(trajectory, "line")
    return trajectory
