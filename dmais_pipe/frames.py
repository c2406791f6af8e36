"""Flight observations frame by frame, assembled in one vectorised pass.

The pose stage, evaluation and the report all walk the flight frames with the same data: each
frame's observations, their world points and their generalized rays. `frame_observations` builds
them once for all frames (one lookup of the points, one ray computation per camera, one sort by
frame) instead of indexing tables per frame.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass

import numpy as np
import pandas as pd

from .dataset import Dataset, factorized
from .rig import Rig


@dataclass(frozen=True)
class ObservationRows:
    """Observations (n of them): cameras, images, point_ids (n,) str; uv: (n, 2) pixels; points:
    (n, 3) world points (m); origins, directions: (n, 3) the generalized rays in the rig frame (the
    paper's v_i, f_i)."""

    cameras: np.ndarray
    images: np.ndarray
    point_ids: np.ndarray
    uv: np.ndarray
    points: np.ndarray
    origins: np.ndarray
    directions: np.ndarray


@dataclass(frozen=True, kw_only=True)
class FrameObservations(ObservationRows):
    """The observations of one flight frame, in the order of the observations table."""

    frame: str
    group: str

    def __len__(self) -> int:
        return len(self.uv)


@dataclass(frozen=True, kw_only=True)
class FlightObservations(ObservationRows):
    """The observations of every flight frame at once, grouped by frame (F frames, N observations).

    frames, groups: (F,) str, sorted by frame id; bounds: (F + 1,) int, frame k's observations are
    rows bounds[k]:bounds[k + 1]; frame_index: (N,) int, each row's frame; point_names (P,) str the
    distinct point ids, sorted, and point_index (N,) int each row's among them (point_ids is
    point_names[point_index]). Every (N, 3) array is C-contiguous, so a frame's rows go to the compiled
    solver without a copy.
    """

    frames: np.ndarray
    groups: np.ndarray
    bounds: np.ndarray
    frame_index: np.ndarray
    point_names: np.ndarray
    point_index: np.ndarray

    def __len__(self) -> int:
        return len(self.frames)

    def frame(self, k: int) -> FrameObservations:
        """Frame k's observations."""
        part = slice(self.bounds[k], self.bounds[k + 1])
        rows = (self.cameras, self.images, self.point_ids, self.uv, self.points, self.origins, self.directions)
        return FrameObservations(*(array[part] for array in rows), frame=str(self.frames[k]),
                                 group=str(self.groups[k]))


def flight_observations_by_frame(dataset: Dataset, rig: Rig, observations: pd.DataFrame,
                                 cameras: Sequence[str] | None = None, groups: Sequence[str] | None = None
                                 ) -> FlightObservations:
    """The flight frames with observations (of `cameras`, of `groups` if given), sorted by frame id,
    with their rays, in one vectorised pass.

    observations: image, camera, point_id, u, v (Workspace.load_observations). Each id is hashed once
    per row and looked up, converted and sorted once per distinct id (`_flight_rows`, `_as_str`); the
    rows are those of dataset.flight_observations sorted by frame stably.
    """
    rows, frame, frames = _flight_rows(dataset, observations, cameras, groups)
    uv = np.column_stack([observations["u"].to_numpy(float)[rows], observations["v"].to_numpy(float)[rows]])
    point_ids, point = _as_str(observations["point_id"].to_numpy(object)[rows])
    xyz = dataset.points.loc[point_ids, ["x", "y", "z"]].to_numpy(float).reshape(-1, 3)
    camera = _as_str(observations["camera"].to_numpy(object)[rows])
    camera = camera[0][camera[1]]
    origins, directions = rig.rays_of(camera, uv) if len(rows) else (np.zeros((0, 3)), np.zeros((0, 3)))
    starts = np.flatnonzero(np.r_[True, frame[1:] != frame[:-1]]) if len(frame) else np.zeros(0, int)
    bounds = np.r_[starts, len(frame)]
    group_of = pd.Series(dataset.frames["group"].to_numpy(str), index=dataset.frames["frame"].to_numpy(str))
    images = _as_str(observations["image"].to_numpy(object)[rows])
    return FlightObservations(camera, images[0][images[1]], point_ids[point], uv, np.ascontiguousarray(xyz[point]),
                              np.ascontiguousarray(origins), np.ascontiguousarray(directions),
                              frames=frames[frame[starts]], groups=group_of.loc[frames[frame[starts]]].to_numpy(str),
                              bounds=bounds, frame_index=np.repeat(np.arange(len(starts)), np.diff(bounds)),
                              point_names=point_ids, point_index=point)


def _flight_rows(dataset: Dataset, observations: pd.DataFrame, cameras: Sequence[str] | None,
                 groups: Sequence[str] | None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The rows (n,) of `observations` on flight images (images.csv's camera one of `cameras`, the frame one of
    `groups`, if given), sorted by frame id stably; each one's frame (n,) among the frames (k,) str sorted."""
    image, names = factorized(observations["image"].to_numpy(object))
    images = dataset.images
    flight = (images["stage"] == "flight").to_numpy()
    if cameras is not None:
        flight = flight & images["camera"].isin(cameras).to_numpy()
    at = pd.Index(images["image"].to_numpy(object)[flight]).get_indexer(names)  # -1: not a flight image
    chosen = at >= 0
    placement = np.full(len(names), None, dtype=object)
    placement[chosen] = images["placement"].to_numpy(object)[flight][at[chosen]]
    if groups:
        group_of = dict(zip(dataset.frames["frame"].to_numpy(str), dataset.frames["group"].to_numpy(str)))
        wanted = set(groups)
        chosen &= np.array([group_of.get(frame) in wanted for frame in placement], dtype=bool)
    frames, frame_of_name = _as_str(placement[chosen])
    frame = np.full(len(names), -1)
    frame[chosen] = frame_of_name
    rows = np.flatnonzero(chosen[image])
    rows = rows[np.argsort(frame[image[rows]], kind="stable")]
    return rows, frame[image[rows]], frames


def _as_str(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distinct (k,), index (n,)) of str objects values (n,): the distinct ones as numpy str, sorted, and each
    value's place among them: distinct[index] is values.astype(str), of its width."""
    codes, uniques = factorized(values)
    distinct, inverse = np.unique(np.asarray(uniques, dtype=object).astype(str), return_inverse=True)
    return distinct, inverse[codes].reshape(-1)


def frame_observations(dataset: Dataset, rig: Rig, observations: pd.DataFrame,
                       cameras: Sequence[str] | None = None, groups: Sequence[str] | None = None
                       ) -> Iterator[FrameObservations]:
    """The flight frames with observations (of `cameras`, of `groups` if given), sorted by frame id
    (`flight_observations_by_frame`, one frame at a time)."""
    flight = flight_observations_by_frame(dataset, rig, observations, cameras, groups)
    for k in range(len(flight)):
        yield flight.frame(k)
