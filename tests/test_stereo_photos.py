"""OpenCV's stereo chessboard photographs (tests/data/chessboard) with the opencv lens model through
intrinsics, extrinsics and pose, against cv2.calibrateCamera + stereoCalibrate + solvePnP
(`dmais bench stereo`, bench/stereo.py)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from dmais_pipe.bench.stereo import bench_stereo


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    work = tmp_path_factory.mktemp("stereo")
    return work, bench_stereo(model="opencv", work=work).set_index("what")


@pytest.fixture(scope="module")
def table(run):
    return run[1]


def test_the_rig_is_watched_over_exact_control_points(run):
    """The board's corners are exact (no sigma_m, the survey term 0): the watched rig's points are
    held at WATCH_MIN_SURVEY_M instead of the group being left out."""
    mounting = pd.read_csv(run[0] / "results" / "poses_stereo_both.mounting.csv")
    assert list(mounting["camera"]) == ["left", "right"]
    assert np.isfinite(mounting.loc[1, ["d_rx_arcmin", "sigma_rx_arcmin", "d_focal_ppm"]].to_numpy(float)).all()


@pytest.mark.parametrize("side", ["left", "right"])
def test_each_cameras_intrinsics_are_opencvs(table, side):
    row = table.loc[f"intrinsics {side} vs calibrateCamera"]
    assert abs(row["focal_pct"]) < 0.1
    assert row["principal_px"] < 1.0
    assert row["eps_eval_px"] <= row["eps_eval_opencv_px"] + 0.005


def test_the_rig_is_stereoCalibrates(table):
    row = table.loc["rig right_from_left vs stereoCalibrate"]
    assert row["position_mm"] < 0.1  # of an 84 mm baseline
    assert row["rotation_arcmin"] < 0.5


@pytest.mark.parametrize("side", ["left", "right"])
def test_one_cameras_pose_is_its_solvePnP(table, side):
    row = table.loc[f"pose {side} vs solvePnP {side}"]
    assert row["frames"] == 13
    assert row["position_mm"] < 0.05 and row["position_max_mm"] < 0.1
    assert row["rotation_arcmin"] < 0.5 and row["rotation_max_arcmin"] < 1.0
    other = table.loc[f"pose {side} vs solvePnP {'right' if side == 'left' else 'left'}"]
    assert other["rotation_arcmin"] > 10 * row["rotation_arcmin"]  # the two solvePnP differ: the check can fail


def test_both_cameras_pose_lies_between_the_two_solvePnP(table):
    apart = table.loc["solvePnP left vs solvePnP right"]
    for side in ("left", "right"):
        row = table.loc[f"pose both vs solvePnP {side}"]
        assert row["position_mm"] < apart["position_mm"] and row["rotation_arcmin"] < apart["rotation_arcmin"]
        assert row["position_max_mm"] <= apart["position_max_mm"]
