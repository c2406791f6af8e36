"""frames.flight_observations_by_frame: every array the same, dtype and bits, as the pandas filter, sort and
lookups it stands in for, on a simulated flight whose observations are shuffled and thinned."""

from __future__ import annotations

import shutil

import numpy as np
import pandas as pd
import pytest

from dmais_pipe.dataset import flight_observations
from dmais_pipe.frames import FlightObservations, flight_observations_by_frame
from dmais_pipe.workspace import Workspace

from conftest import observation_only

SIM = observation_only("frames-small", seed=11, calib_images=2, eval_images=1, frames_per_group=30)


def _reference(dataset, rig, observations, cameras=None, groups=None) -> FlightObservations:
    """The frames in a few pandas steps: the flight rows, their frames' groups, a stable sort by frame id."""
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
    point_names, point_index = np.unique(obs["point_id"].to_numpy(str), return_inverse=True)
    return FlightObservations(camera, obs["image"].to_numpy(str), obs["point_id"].to_numpy(str), uv, points,
                              np.ascontiguousarray(origins), np.ascontiguousarray(directions), frames=frames,
                              groups=group_of.loc[frames].to_numpy(str), bounds=bounds,
                              frame_index=np.repeat(np.arange(len(starts)), np.diff(bounds)),
                              point_names=point_names, point_index=point_index)


@pytest.fixture(scope="module")
def workspace(simulated_dataset, tmp_path_factory):
    dataset = simulated_dataset(SIM)
    results = tmp_path_factory.mktemp("frames")
    shutil.copy(dataset / "truth" / "rig.json", results / "rig.json")
    return Workspace.open(dataset, results)


@pytest.mark.parametrize("order", ["as loaded", "shuffled", "thinned"])
@pytest.mark.parametrize("selection", [{}, {"cameras": ["C2", "C0"]}, {"groups": ["2"]},
                                       {"cameras": ["C1"], "groups": ["1", "2"]}, {"groups": ["none"]}])
def test_flight_frames_are_the_pandas_ones_bit_for_bit(workspace, order, selection):
    observations = workspace.load_observations()
    rng = np.random.default_rng(2)
    if order == "shuffled":  # an image's markers no longer in a row
        observations = observations.iloc[rng.permutation(len(observations))].reset_index(drop=True)
    elif order == "thinned":
        observations = observations[rng.random(len(observations)) < 0.6].reset_index(drop=True)
    rig = workspace.load_rig()
    expected = _reference(workspace.dataset, rig, observations, **selection)
    flight = flight_observations_by_frame(workspace.dataset, rig, observations, **selection)
    assert len(flight.uv) == len(expected.uv) and (len(flight.uv) > 0) == (selection != {"groups": ["none"]})
    for name in FlightObservations.__dataclass_fields__:
        got, want = getattr(flight, name), getattr(expected, name)
        assert got.dtype == want.dtype and got.shape == want.shape, name
        assert got.flags.c_contiguous == want.flags.c_contiguous, name
        assert got.tobytes() == want.tobytes(), name
