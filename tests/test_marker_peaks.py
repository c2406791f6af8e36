"""`detect.saddle_peaks` (the maxima among the few above the threshold) against the whole-level masks it
replaces, np.nonzero((response >= dilated) & (response > threshold)): the same positions, order and dtypes."""

import importlib

import cv2
import numpy as np
import pytest

detection = importlib.import_module("dmais_pipe.markers.detect")  # the module (the package's `detect` is the function)


def _reference(response: np.ndarray, min_contrast: float):
    threshold = np.float32((detection.RESPONSE_FACTOR * min_contrast) ** 2 * 1e4)
    peaks = cv2.dilate(response, np.ones((3, 3), np.uint8))
    ys, xs = np.nonzero((response >= peaks) & (response > threshold))
    return ys, xs, response[ys, xs]


@pytest.mark.parametrize("seed", range(4))
def test_saddle_peaks_are_the_masks(seed):
    rng = np.random.default_rng(seed)
    for shape in ((1, 1), (1, 7), (5, 1), (37, 53), (169, 168), (300, 410)):
        level = cv2.GaussianBlur(rng.normal(100.0, 40.0, shape).astype(np.float32), (0, 0), 1.5)
        level[: shape[0] // 3, : shape[1] // 4] = np.round(level[: shape[0] // 3, : shape[1] // 4] / 20.0) * 20.0
        responses = [detection.saddle_response(level), np.round(detection.saddle_response(level) / 50.0) * 50.0]
        odd = responses[0].copy()
        odd.flat[:: 17] = np.nan
        odd.flat[5:: 29] = np.inf
        for response in responses + [odd, np.zeros(shape, np.float32), responses[0][:, ::-1]]:
            for min_contrast in (0.0, 5.0, 50.0):
                got, want = detection.saddle_peaks(response, min_contrast), _reference(response, min_contrast)
                for a, b in zip(got, want):
                    assert a.dtype == b.dtype and np.array_equal(a, b, equal_nan=True)
