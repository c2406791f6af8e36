"""Detection on textured ground (grass, gravel in sun): the ground's texture saddles are no markers."""

from __future__ import annotations

import importlib

import cv2
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


SMALL = {"camera": Camera(8000.0, 8000.0, 159.5, 119.5, 0.0, 320, 240), "slots": np.array([[160.0, 120.0]])}


def test_a_small_marker_within_the_texture_contrast_is_found_by_its_sharp_ring():
    """A 14 px marker (clean to ~5 px, score ~0.46 < TEXTURE_MIN_SCORE): found on quiet ground, on
    25 DN texture (contrast above TEXTURE_FACTOR x the clutter) and on 40 DN texture, where its
    contrast is within the texture's and its ring, a square wave, is what tells it from a smooth
    saddle: without the sharpness test it is rejected with the texture reason there (as it was)."""
    small = {**SMALL, "sizes_px": (14.0, 14.0), "max_tilt_deg": 0.0}
    for std in (0.0, 25.0, 40.0):
        image, truth = scene(std, 1.2, 0, **small)
        found = detection.detect(image)
        assert len(found) == 1 and errors(found, truth)[0] < 0.05
        assert found["score"].iloc[0] < detection.TEXTURE_MIN_SCORE
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(detection, "SHARP_QUALITY", 1.01)  # the sharpness test off
        found, rejected = detection.detect(image, with_rejected=True)
    assert len(found) == 0
    near = rejected[np.hypot(rejected["u"] - truth[0, 0], rejected["v"] - truth[0, 1]) < 1.0]
    assert list(near["reason"]) == [detection.TEXTURE]


def test_a_faint_steep_marker_on_strong_texture_is_found():
    """A 30 px marker of 75-100 DN seen at up to 60 deg (15 px across) on 40 DN texture blurred by
    1.2 px: its contrast is within the texture's and it stays a clean X to 7.4 px only, so the
    score alone called it texture (seed 44; with 75-170 DN, 58 markers of 600 scenes); its sharp
    ring keeps it, to sub-pixel accuracy."""
    faint = {**SMALL, "sizes_px": (30.0, 30.0), "max_tilt_deg": 60.0, "contrasts_dn": (75.0, 100.0)}
    image, truth = scene(40.0, 1.2, 44, **faint)
    found = detection.detect(image)
    assert len(found) == 1 and errors(found, truth)[0] < 0.05
    assert found["score"].iloc[0] < detection.TEXTURE_MIN_SCORE
    img = image.astype(np.float32)
    contrast = detection._probe_ring(img, truth, np.array([7.38]))[1]
    assert abs(contrast[0]) < detection.TEXTURE_FACTOR * detection.clutter(cv2.pyrDown(img))


def test_a_faint_marker_beyond_the_strongest_saddle_peaks_is_still_a_candidate(monkeypatch):
    """On strong texture a faint marker's saddle peak need not be among the MAX_CANDIDATES strongest
    (a 12 MP image of 40 DN texture has ~220,000 peaks, and the marker's ranked up to ~70,000): with
    the cap scaled to this 320 x 240 image's ~1,100 peaks (100), the marker's peak ranks ~200 (seed
    24, 2 px texture blur), and its rings, an X to 8 px, keep it a candidate (it was lost)."""
    faint = {**SMALL, "sizes_px": (30.0, 120.0), "max_tilt_deg": 60.0, "contrasts_dn": (75.0, 170.0)}
    image, truth = scene(40.0, 2.0, 24, **faint)
    monkeypatch.setattr(detection, "MAX_CANDIDATES", 100)
    img = image.astype(np.float32)
    level = cv2.pyrDown(img)
    ys, xs, strength = detection.saddle_peaks(detection.saddle_response(level), detection.MIN_CONTRAST)
    strongest = detection.strongest(2 * xs, 2 * ys, strength)
    assert len(xs) > 1000 and cKDTree(strongest).query(truth)[0][0] > 5.0  # not among the strongest
    assert np.any(cKDTree(detection.candidates(img, detection.MIN_CONTRAST)).query(truth)[0] < 2.5)
    found = detection.detect(image)
    assert len(found) == 1 and errors(found, truth)[0] < 0.05


def test_sharpness_tells_a_square_wave_ring_from_a_smooth_saddle():
    """On rings about its centre a smooth saddle (x^2 - y^2, any scale) is a sinusoid of twice the
    angle: quality 8 / pi^2 = 0.81, below SHARP_QUALITY, whatever its contrast; an X-corner blurred
    by 0.8 px, at its edges, scores above it from a clean radius of 5.5 px."""
    y, x = np.mgrid[0:64, 0:64].astype(np.float32) - 32.0
    centre, radius = np.array([[32.0, 32.0]]), np.array([5.47, 7.38, 13.45])
    for curvature in (0.05, 0.5):
        saddle = 110.0 + curvature * (x**2 - y**2)
        quality = detection.sharpness(saddle, np.repeat(centre, 3, axis=0), radius)
        np.testing.assert_allclose(quality, 8 / np.pi**2, atol=0.01)
    corner = cv2.GaussianBlur(np.where(x * y > 0, 205.0, 35.0).astype(np.float32), (0, 0), 0.8)
    assert np.all(detection.sharpness(corner, np.repeat(centre, 3, axis=0), radius) > detection.SHARP_QUALITY + 0.05)
