"""stages.pose.watch_rig: the groups' adjustments from the per-observation table by ids looked up once per
distinct id, to the last bit those of the pandas selections and lookups per group it stands in for."""

from __future__ import annotations

import shutil

import numpy as np
import pandas as pd
import pytest

from dmais_pipe.dataset import FRAME_COLUMNS, point_sigma
from dmais_pipe.errors import DmaisError
from dmais_pipe.geometry import rotation_from_quat
from dmais_pipe.pose.error_model import calibration_parameters, survey_sigma
from dmais_pipe.pose.mounting import adjust_group_rig
from dmais_pipe.stages import pose
from dmais_pipe.workspace import QUAT, TRANSLATION, Workspace

from conftest import observation_only

SIM = observation_only("watch-small", seed=13, calib_images=2, eval_images=1, frames_per_group=12)


def _reference(dataset, rig, solved, calibrated_noise, lever_arm=None, pos_sigma=None, calibration=None):
    """watch_rig as pandas steps: per group, its frames' rows selected, their points looked up per row."""
    used = solved.observations[solved.observations["used"].to_numpy(bool)]
    points, pos = dataset.points, dataset.frames.set_index("frame")[list(FRAME_COLUMNS[2:])]
    watched = {}
    for group, model in solved.error_model.items():
        frames = solved.table[solved.table["group"].astype(str) == str(group)]
        rows = used[used["frame"].isin(set(frames["frame"]))]
        pixel = max(model.sigma["pixel"], calibrated_noise if np.isfinite(calibrated_noise) else 0.0,
                    pose.WATCH_MIN_PIXEL_PX)
        rotation = float(np.hypot(model.sigma["jitter"], model.sigma["mounting"]))
        survey = np.maximum(survey_sigma(point_sigma(points, rows["point_id"]), model), pose.WATCH_MIN_SURVEY_M)
        R = rotation_from_quat(frames[list(QUAT)].to_numpy(float))
        centres = {} if lever_arm is None else {
            "center_prior_m": pos.loc[frames["frame"]].to_numpy(float) - np.einsum("fji,j->fi", R, lever_arm),
            "center_sigma_m": pos_sigma}
        try:
            watched[str(group)] = adjust_group_rig(
                rig, rows["camera"].to_numpy(), rows[["u", "v"]].to_numpy(float), rows["point_id"].to_numpy(),
                points.loc[rows["point_id"], ["x", "y", "z"]].to_numpy(float),
                pd.Index(frames["frame"]).get_indexer(rows["frame"]), R, frames[list(TRANSLATION)].to_numpy(float),
                pixel, rotation, survey, **centres, calibration_covariance=calibration)
        except DmaisError:
            pass
    return watched


@pytest.fixture(scope="module")
def solved(simulated_dataset, tmp_path_factory):
    dataset = simulated_dataset(SIM)
    results = tmp_path_factory.mktemp("watch")
    shutil.copy(dataset / "truth" / "rig.json", results / "rig.json")
    workspace = Workspace.open(dataset, results)
    rig = workspace.load_rig()
    record = pose._rig_record(workspace)
    calibration = pose.calibration_covariance(record, rig.camera_names, calibration_parameters(rig))
    solution = pose._solve(workspace, pose.Conf(), rig, record, calibration, rig.camera_names, None)
    return workspace.dataset, rig, solution, calibration


@pytest.mark.parametrize("variant", ["as solved", "observations shuffled", "a lever arm", "a group unused"])
def test_watched_rigs_are_the_pandas_selections_ones_bit_for_bit(solved, variant):
    dataset, rig, solution, calibration = solved
    prior = (None, None)
    if variant == "observations shuffled":
        order = np.random.default_rng(3).permutation(len(solution.observations))
        solution = type(solution)(solution.table, solution.observations.iloc[order].reset_index(drop=True),
                                  solution.error_model, solution.budget, solution.covariance)
    elif variant == "a lever arm":
        prior = (np.array([0.1, -0.05, 0.3]), np.array([0.02, 0.02, 0.03]))
    elif variant == "a group unused":  # its observations none used: the adjustment refuses it, as before
        group = sorted(solution.error_model)[0]
        frames = set(solution.table.loc[solution.table["group"].astype(str) == str(group), "frame"])
        observations = solution.observations.copy()
        observations.loc[observations["frame"].isin(frames), "used"] = False
        solution = type(solution)(solution.table, observations, solution.error_model, solution.budget,
                                  solution.covariance)
    expected = _reference(dataset, rig, solution, 0.3, *prior, calibration=calibration)
    watched = pose.watch_rig(dataset, rig, solution, 0.3, *prior, calibration=calibration)
    assert list(watched) == list(expected)
    assert len(watched) == len(solution.error_model) - (variant == "a group unused") > 1
    for group, result in watched.items():
        want = expected[group]
        for name in ("delta_arcmin", "sigma_arcmin", "covariance_arcmin2", "chi2", "significant", "focal_ppm",
                     "sigma_focal_ppm", "R", "t"):
            np.testing.assert_array_equal(getattr(result, name), getattr(want, name), err_msg=name)
        assert (result.iterations, result.cost, result.dof) == (want.iterations, want.cost, want.dof)
