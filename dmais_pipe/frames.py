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
class FrameObservations:
    """The observations of one flight frame (n of them, in the order of the observations table).

    cameras, images, point_ids: (n,) str; uv: (n, 2) pixels; points: (n, 3) world points (m);
    origins, directions: (n, 3) the generalized rays in the rig frame (the paper's v_i, f_i).
    """

    frame: str
    group: str
    cameras: np.ndarray
    images: np.ndarray
    point_ids: np.ndarray
    uv: np.ndarray
    points: np.ndarray
    origins: np.ndarray
    directions: np.ndarray

    def __len__(self) -> int:
        return len(self.uv)


def frame_observations(dataset: Dataset, rig: Rig, observations: pd.DataFrame,
                       cameras: Sequence[str] | None = None, groups: Sequence[str] | None = None
                       ) -> Iterator[FrameObservations]:
    """The flight frames with observations (of `cameras`, of `groups` if given), sorted by frame id.

    observations: image, camera, point_id, u, v (Workspace.load_observations).
    """
    obs = flight_observations(dataset, observations, cameras)
    group_of = dict(zip(dataset.frames["frame"], dataset.frames["group"]))
    if groups:
        obs = obs[obs["frame"].map(group_of).isin(list(groups))]
    obs = obs.sort_values("frame", kind="stable")
    camera = obs["camera"].to_numpy(str)
    uv = obs[["u", "v"]].to_numpy(float)
    points = dataset.points.loc[obs["point_id"], ["x", "y", "z"]].to_numpy(float)
    origins, directions = rig.rays_of(camera, uv) if len(obs) else (np.zeros((0, 3)), np.zeros((0, 3)))
    frame = obs["frame"].to_numpy(str)
    starts = np.flatnonzero(np.r_[True, frame[1:] != frame[:-1]]) if len(frame) else np.zeros(0, int)
    image, point_id = obs["image"].to_numpy(str), obs["point_id"].to_numpy(str)
    for start, stop in zip(starts, np.r_[starts[1:], len(frame)]):
        part = slice(start, stop)
        yield FrameObservations(frame[start], str(group_of[frame[start]]), camera[part], image[part],
                                point_id[part], uv[part], points[part], origins[part], directions[part])
