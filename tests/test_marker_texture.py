"""Detection on textured ground (grass, gravel in sun): the ground's texture saddles are no markers."""

from __future__ import annotations

import importlib

import numpy as np
import pytest
from scipy.spatial import cKDTree

from dmais_pipe.bench.marker_scenes import textured_scene
from dmais_pipe.camera import Camera

detection = importlib.import_module("dmais_pipe.markers.detect")  # the module, not the function

CAMERA = Camera(8000.0, 8000.0, 319.5, 239.5, 0.0, 640, 480)
SLOTS = np.array([[160.0, 240.0], [480.0, 240.0]])
# (texture std DN, texture blur px, seed): images where detection without the texture rule
# returns 2 and 3 saddles of the texture besides both markers.
TEXTURED = [(25.0, 1.2, 0), (40.0, 1.2, 1)]


def scene(std: float, blur: float, seed: int, **options):
    """(image (480, 640) uint8, truth (n, 2)) of markers of 30-120 px on textured ground."""
    options = {"camera": CAMERA, "slots": SLOTS, "sizes_px": (30.0, 120.0), **options}
    return textured_scene(np.random.default_rng(seed), std, blur, **options)


def errors(found, truth: np.ndarray) -> np.ndarray:
    """(k,) distance (px) of each detection of `found` to the nearest true corner of truth (n, 2)."""
    return cKDTree(truth).query(found[["u", "v"]].to_numpy())[0] if len(found) else np.zeros(0)


@pytest.fixture(scope="module")
def detected():
    """Per TEXTURED case: (truth, detections and rejections, detections without the texture rule)."""
    out = {}
    for std, blur, seed in TEXTURED:
        image, truth = scene(std, blur, seed)
        found, rejected = detection.detect(image, with_rejected=True)
        with pytest.MonkeyPatch.context() as patch:
            patch.setattr(detection, "TEXTURE_MIN_SCORE", 0.0)  # the rule off
            unruled = detection.detect(image)
        out[std, blur, seed] = truth, found, rejected, unruled
    return out


@pytest.mark.parametrize("case", TEXTURED)
def test_markers_on_textured_ground_without_false_detections(detected, case):
    truth, found, _, _ = detected[case]
    error = errors(found, truth)
    assert np.all(error < 0.05)  # every detection is a marker, to sub-pixel accuracy
    assert len(found) == len(truth)
    assert np.all(cKDTree(found[["u", "v"]].to_numpy()).query(truth)[0] < 0.05)


@pytest.mark.parametrize("case", TEXTURED)
def test_texture_saddles_are_rejected_with_the_texture_reason(detected, case):
    truth, _, rejected, unruled = detected[case]
    saddles = unruled[errors(unruled, truth) >= 1.0][["u", "v"]].to_numpy()
    assert len(saddles) >= 2  # without the rule the ground's texture is detected
    textured = rejected[rejected["reason"] == detection.TEXTURE][["u", "v"]].to_numpy(dtype=float)
    assert np.all(cKDTree(textured).query(saddles)[0] < 1e-6)


def test_a_small_marker_is_texture_where_its_contrast_is_within_the_texture():
    """A 14 px marker (clean to ~7 px, score ~0.65 < TEXTURE_MIN_SCORE): found on quiet ground and
    on 25 DN texture (contrast above TEXTURE_FACTOR x the clutter), rejected with the texture
    reason on 40 DN texture, found there too with a lower TEXTURE_FACTOR."""
    small = {"camera": Camera(8000.0, 8000.0, 159.5, 119.5, 0.0, 320, 240), "slots": np.array([[160.0, 120.0]]),
             "sizes_px": (14.0, 14.0), "max_tilt_deg": 0.0}
    for std in (0.0, 25.0):
        image, truth = scene(std, 1.2, 0, **small)
        found = detection.detect(image)
        assert len(found) == 1 and errors(found, truth)[0] < 0.05
        assert found["score"].iloc[0] < detection.TEXTURE_MIN_SCORE
    image, truth = scene(40.0, 1.2, 0, **small)
    found, rejected = detection.detect(image, with_rejected=True)
    assert len(found) == 0
    near = rejected[np.hypot(rejected["u"] - truth[0, 0], rejected["v"] - truth[0, 1]) < 1.0]
    assert list(near["reason"]) == [detection.TEXTURE]
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(detection, "TEXTURE_FACTOR", 10.0)
        found = detection.detect(image)
    assert len(found) == 1 and errors(found, truth)[0] < 0.05
