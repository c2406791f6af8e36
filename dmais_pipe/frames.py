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

from .dataset import Dataset, flight_observations
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
    rows bounds[k]:bounds[k + 1]; frame_index: (N,) int, each row's frame. Every (N, 3) array is
    C-contiguous, so a frame's rows go to the compiled solver without a copy.
    """

    frames: np.ndarray
    groups: np.ndarray
    bounds: np.ndarray
    frame_index: np.ndarray

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

    observations: image, camera, point_id, u, v (Workspace.load_observations).
    """
    obs = flight_observations(dataset, observations, cameras)
    group_of = pd.Series(dataset.frames["group"].to_numpy(str), index=dataset.frames["frame"].to_numpy(str))
    if groups:
        obs = obs[obs["frame"].map(group_of).isin(list(groups))]
    obs = obs.sort_values("frame", kind="stable")
    camera = obs["camera"].to_numpy(str)
    uv = np.ascontiguousarray(obs[["u", "v"]].to_numpy(float))
    points = np.ascontiguousarray(dataset.points.loc[obs["point_id"], ["x", "y", "z"]].to_numpy(float))
    origins, directions = rig.rays_of(camera, uv) if len(obs) else (np.zeros((0, 3)), np.zeros((0, 3)))
    frame = obs["frame"].to_numpy(str)
    starts = np.flatnonzero(np.r_[True, frame[1:] != frame[:-1]]) if len(frame) else np.zeros(0, int)
    frames, bounds = frame[starts], np.r_[starts, len(frame)]
    return FlightObservations(camera, obs["image"].to_numpy(str), obs["point_id"].to_numpy(str), uv, points,
                              np.ascontiguousarray(origins), np.ascontiguousarray(directions), frames=frames,
                              groups=group_of.loc[frames].to_numpy(str), bounds=bounds,
                              frame_index=np.repeat(np.arange(len(starts)), np.diff(bounds)))


def frame_observations(dataset: Dataset, rig: Rig, observations: pd.DataFrame,
                       cameras: Sequence[str] | None = None, groups: Sequence[str] | None = None
                       ) -> Iterator[FrameObservations]:
    """The flight frames with observations (of `cameras`, of `groups` if given), sorted by frame id
    (`flight_observations_by_frame`, one frame at a time)."""
    flight = flight_observations_by_frame(dataset, rig, observations, cameras, groups)
    for k in range(len(flight)):
        yield flight.frame(k)
