"""Identification in a wide field of view (markers/identify.py, `projective`): a prior attitude off by
a degree about an image axis moves a 60 deg camera's predictions by a keystone that no similarity
takes up; the projective terms do."""

from __future__ import annotations

import numpy as np
import pytest

from dmais_pipe.camera import Camera
from dmais_pipe.geometry import Rigid3, exp_so3
from dmais_pipe.markers.extract import wide_field
from dmais_pipe.markers.identify import identify

OBLIQUE = Camera(12000.0, 12000.0, 6999.5, 4999.5, -0.03, 14000, 10000, "opencv", k2=0.01, p1=3e-5, p2=-4e-5)


def scene(seed: int, turn_deg: float):
    """Detections (n, 2) of an 11 x 9 grid of points 0.3-1.4 km ahead of a 45 deg oblique camera, with
    0.3 px noise, and the predictions (n, 2) of the same points from a prior turned by turn_deg about
    a random image axis, made with the pinhole of the same focal length (no distortion known)."""
    rng = np.random.default_rng(seed)
    x, y = np.meshgrid(np.linspace(-500, 500, 11), np.linspace(300, 1400, 9))
    points = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)]) + rng.normal(0, 20, (x.size, 3))
    tilt = np.radians(45.0)
    R = np.array([[1.0, 0.0, 0.0], [0.0, -np.sin(tilt), -np.cos(tilt)], [0.0, np.cos(tilt), -np.sin(tilt)]])
    cam_from_world = Rigid3(R, -R @ np.array([0.0, 0.0, 600.0]))
    detections = OBLIQUE.project(cam_from_world.apply(points)) + rng.normal(0, 0.3, (len(points), 2))
    axis = np.r_[rng.normal(size=2), 0.0]
    turned = Rigid3(exp_so3(np.radians(turn_deg) * axis / np.linalg.norm(axis)), np.zeros(3)) * cam_from_world
    pinhole = Camera(OBLIQUE.fx, OBLIQUE.fy, OBLIQUE.cx, OBLIQUE.cy, 0.0, OBLIQUE.width, OBLIQUE.height)
    seen = OBLIQUE.in_image(np.nan_to_num(detections, nan=-1e9))
    return detections[seen], pinhole.project(turned.apply(points[seen]))


def test_a_wide_field_is_one_and_the_dmais_is_not():
    assert wide_field(OBLIQUE)
    assert not wide_field(Camera(45000.0, 45000.0, 2047.5, 1499.5, 3.0, 4096, 3000))


@pytest.mark.parametrize("seed", [1, 2, 3])
def test_the_keystone_of_a_turned_prior_is_modelled_in_a_wide_field(seed):
    detections, predicted = scene(seed, turn_deg=1.0)
    ids = np.array([f"P{k}" for k in range(len(predicted))], dtype=object)
    named = identify(detections, predicted, ids, (OBLIQUE.width, OBLIQUE.height), projective=True)
    given = named != ""
    assert given.mean() >= 0.95
    assert (named[given] == ids[given]).all()  # no wrong id
    similarity = identify(detections, predicted, ids, (OBLIQUE.width, OBLIQUE.height))
    assert (similarity != "").sum() < 0.8 * given.sum()  # the similarity alone loses the corners or everything
