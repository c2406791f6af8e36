"""pose.mounting's inputs and bookkeeping around the adjustment: the fast ways of numbering the cameras and
points, building the columns, the points' offsets and keeping the model at the minimum, each against the
plain way it stands in for (seeded groups of tests/test_mounting.py)."""

from __future__ import annotations

import numpy as np
import pytest

from dmais_pipe.pose import _group, mounting
from dmais_pipe.pose.mounting import adjust_group_rig

from test_mounting import focal_covariance, make_group, noise


def _same_result(a, b) -> None:
    """Two GroupRigs equal to the last bit."""
    for name in ("delta_arcmin", "sigma_arcmin", "covariance_arcmin2", "chi2", "significant", "focal_ppm",
                 "sigma_focal_ppm", "R", "t"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert (a.cameras, a.iterations, a.cost, a.dof, a.n_frames) == (b.cameras, b.iterations, b.cost, b.dof, b.n_frames)


@pytest.mark.parametrize("kind", ["names", "ids", "mixed lengths", "one"])
def test_distinct_strings_are_numpys_unique(kind):
    rng = np.random.default_rng(7)
    pool = {"names": ["C0", "C1", "C2", "C3", "C4"], "ids": [f"GA{k:03d}" for k in range(90)],
            "mixed lengths": ["b", "a10", "a9", "a", "Z", "é", "a_1"], "one": ["x"]}[kind]
    values = np.array([pool[k] for k in rng.integers(0, len(pool), 2000)], dtype=object)
    expected = np.unique(values.astype(str), return_inverse=True)
    for given in (values, values.astype(str), list(values)):
        distinct, inverse = mounting._distinct(np.asarray(given))
        assert distinct.dtype == expected[0].dtype
        np.testing.assert_array_equal(distinct, expected[0])
        np.testing.assert_array_equal(inverse, expected[1])


def test_an_adjustment_of_object_arrays_is_that_of_numpy_strings():
    """A table's columns (str objects, numbered by hashing) and numpy's fixed-width strings (sorted) give
    the same adjustment to the last bit."""
    group = make_group(6, frames=4, mount_arcmin=1.0)
    calibration = focal_covariance(group.rig, np.array([3e-4, 2e-4, 0.0, 4e-4, 2.5e-4]))
    arguments = (group.uv, group.point_ids, group.points, group.frame_index, group.R, group.t)
    as_numpy = adjust_group_rig(group.rig, group.cameras, *arguments, **noise(), calibration_covariance=calibration)
    as_objects = adjust_group_rig(group.rig, group.cameras.astype(object), group.uv, group.point_ids.astype(object),
                                  *arguments[2:], **noise(), calibration_covariance=calibration)
    _same_result(as_numpy, as_objects)


def test_the_model_kept_at_the_minimum_is_the_one_made_again(monkeypatch):
    group = make_group(7, frames=4, mount_arcmin=1.0)
    calibration = focal_covariance(group.rig, np.array([3e-4, 2e-4, 0.0, 4e-4, 2.5e-4]))
    kept = group.adjust(**noise(), calibration_covariance=calibration)
    monkeypatch.setattr(mounting, "KEPT_FORWARD_OBSERVATIONS", 0)
    _same_result(kept, group.adjust(**noise(), calibration_covariance=calibration))


def test_columns_per_camera_are_those_per_observation():
    group = make_group(8, frames=3, markers_per_camera=4)
    for calibration in (None, focal_covariance(group.rig, np.array([3e-4, 0.0, 2e-4, 4e-4, 0.0]))):
        for vibration in (0.3, 0.0):
            problem = mounting._problem(group.rig, group.cameras, group.uv, group.point_ids, group.points,
                                        group.frame_index, group.R, 0.5, vibration, 0.025, 30.0, None, None,
                                        calibration)
            local, rig = mounting._columns(problem)
            K, slot = len(problem.free), np.maximum(problem.slot, 0)
            expected_local = np.broadcast_to(np.arange(6), (len(slot), 6))
            if problem.local_size > 6:
                expected_local = np.concatenate([expected_local, 6 + 3 * slot[:, None] + np.arange(3)], axis=1)
            expected_rig = 3 * slot[:, None] + np.arange(3)
            if len(problem.focal_prior):
                expected_rig = np.concatenate(
                    [expected_rig, 3 * K + np.maximum(problem.focal_slot[problem.camera], 0)[:, None]], axis=1)
            np.testing.assert_array_equal(local, expected_local)
            np.testing.assert_array_equal(rig, expected_rig)


def test_points_in_cameras_give_the_offsets_from_the_centroids_as_numpy_does():
    rng = np.random.default_rng(9)
    F, C, P, N = 6, 5, 20, 300
    frame, point = rng.integers(0, F, N), rng.integers(0, P, N)
    image = frame * C + rng.integers(0, C, N)
    R, t = rng.normal(size=(F, 3, 3)), rng.normal(size=(F, 3)) * 100
    points, cam_from_rig = rng.normal(size=(P, 3)) * 50, rng.normal(size=(F * C, 3, 3))
    cam_t = rng.normal(size=(F * C, 3))
    centre = rng.normal(size=(F, 3)) * 100
    x_rig, x, q = np.empty((N, 3)), np.empty((N, 3)), np.empty((N, 3))
    _group.mounting_points_in_cameras(frame, point, image, R, t, points, cam_from_rig, cam_t, x_rig, x, centre, q)
    alone_rig, alone = np.empty((N, 3)), np.empty((N, 3))
    _group.mounting_points_in_cameras(frame, point, image, R, t, points, cam_from_rig, cam_t, alone_rig, alone)
    np.testing.assert_array_equal(x_rig, alone_rig)
    np.testing.assert_array_equal(x, alone)
    np.testing.assert_array_equal(q, x_rig - centre[frame])
