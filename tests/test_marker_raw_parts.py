"""The windows' parts read from the 8- or 16-bit image itself (`rings.ImageParts(raw=...)`,
`windows._raw_parts`: each pixel read as float32 where it is read, none converted before) against the
same parts converted to float32, through every reader (samples, ring samples, clean radii, the centring's
steps, the fit windows' pixels, integer indexing), to the last bit; and the windowed detection with those
parts reading nothing beyond READ_PX about its windows (the rest of the image poisoned)."""

from __future__ import annotations

import copy
import importlib

import numpy as np
import pandas as pd
import pytest

from dmais_pipe.dataset import Dataset
from dmais_pipe.markers.detect import detect
from dmais_pipe.markers.extract import _prediction_model, search_windows
from dmais_pipe.markers.rings import ImageParts, clean_radius, ring_offsets, ring_sample, sample
from dmais_pipe.markers.windows import detect_in_windows
from dmais_pipe.rig import Rig
from dmais_pipe.sim.config import DEFAULTS

centring = importlib.import_module("dmais_pipe.markers.centring")
windows = importlib.import_module("dmais_pipe.markers.windows")
xfit = importlib.import_module("dmais_pipe.markers.xfit")


def _both(raw: np.ndarray, bounds):
    """(parts reading raw, the same parts converted to float32)."""
    converted = ImageParts(bounds, raw.shape)
    for pixels, top, left in zip(converted.pixels, converted.tops, converted.lefts):
        pixels[...] = raw[top:top + pixels.shape[0], left:left + pixels.shape[1]]
    return ImageParts(bounds, raw.shape, raw=raw), converted


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("bounds", [[(64, 40, 300, 250)], [(0, 0, 192, 180), (256, 100, 460, 300)]])
def test_parts_of_the_raw_image_read_as_the_converted_ones(dtype, bounds):
    rng = np.random.default_rng(140)
    yy, xx = np.mgrid[0:300, 0:460]
    top = np.iinfo(dtype).max
    image = (0.5 * top + 0.3 * top * np.sign((xx - 130.3) * (yy - 120.6)) + rng.normal(0, 0.05 * top, xx.shape))
    raw = np.clip(image, 0, top).astype(dtype)
    parts, converted = _both(raw, bounds)
    uv = np.vstack([[[130.3, 120.6], [131, 121], [np.nan, 5], [2, 2], [459, 299], [350.5, 200.25]],
                    rng.uniform(-0.05, 1.05, (300, 2)) * [460, 300], [130.3, 120.6] + rng.normal(0, 2.0, (40, 2))])
    xy = (uv + rng.normal(0, 0.3, uv.shape)).astype(np.float32)
    assert sample(parts, xy).tobytes() == sample(converted, xy).tobytes()
    for radius, k in ((4.0, 24), (5.0, 48), (60.0, 48)):
        assert ring_sample(parts, uv, ring_offsets(radius, k)).tobytes() == \
            ring_sample(converted, uv, ring_offsets(radius, k)).tobytes()
    assert clean_radius(parts, uv).tobytes() == clean_radius(converted, uv).tobytes()
    limit = np.full(len(uv), 3.0)
    assert centring._refine_fixed(parts, uv, 5.0, 4, 0.01, limit, False).tobytes() == \
        centring._refine_fixed(converted, uv, 5.0, 4, 0.01, limit, False).tobytes()
    centres = np.nan_to_num(uv[:60], nan=10.0)
    for got, want in zip(xfit.window(parts, centres, 7.0), xfit.window(converted, centres, 7.0)):
        assert got.dtype == want.dtype and got.tobytes() == want.tobytes()
    ys, xs = rng.integers(-5, 305, 500), rng.integers(-5, 465, 500)
    for index in ((ys, xs), (ys.astype(np.int32), xs.astype(np.uint32).astype(np.int32)), (ys[:1], xs[:1])):
        got, want = parts[index], converted[index]
        assert got.dtype == np.float32 and got.tobytes() == want.tobytes()


def test_raw_parts_are_made_only_of_8_and_16_bit_c_ordered_images():
    members = [np.array([[10.0, 10.0, 30.0, 30.0]])]
    assert windows._raw_parts(np.zeros((100, 120), np.uint16), members) is not None
    assert windows._raw_parts(np.zeros((100, 120), np.float32), members) is None
    assert windows._raw_parts(np.zeros((100, 240), np.uint8)[:, ::2], members) is None
    with pytest.raises(ValueError):
        ImageParts([(0, 0, 10, 10)], (100, 120), raw=np.zeros((100, 120), np.int32))


SCALE = 0.25


def _small_rig() -> dict:
    rig = copy.deepcopy(DEFAULTS["rig"])
    rig["width"], rig["height"] = int(rig["width"] * SCALE), int(rig["height"] * SCALE)
    rig["nominal_focal_px"] *= SCALE
    for entry in rig["cameras"].values():
        for key in ("fx", "fy", "cx", "cy"):
            entry[key] *= SCALE
    return rig


#: One rendered frame of the five cameras (tests/test_marker_windows.py's), the windows at 0.2 deg.
FLIGHT = {
    "name": "windows",
    "seed": 4040,
    "rig": _small_rig(),
    "render": {"intrinsics": False, "extrinsics": False, "flight": True},
    "intrinsics": {"calib_images_per_camera": 3, "eval_images_per_camera": 0},
    "flight": {"sites": {"A": {"center_m": [1500.0, -800.0, 45.0], "groups": [1]}}, "frames_per_group": 1,
               "ins_attitude_sigma_deg": 0.02, "ins_boresight_deg": [0.0, 0.0, 0.0]},
}


def _in(frame: pd.DataFrame, boxes: np.ndarray) -> pd.DataFrame:
    uv = frame[["u", "v"]].to_numpy(dtype=float)
    inside = ((uv[:, None] >= boxes[None, :, :2]) & (uv[:, None] <= boxes[None, :, 2:])).all(axis=2).any(axis=1)
    return frame[inside].reset_index(drop=True)


def _sorted(rejected: pd.DataFrame) -> pd.DataFrame:
    return rejected.sort_values(["v", "u", "reason"], ignore_index=True)


@pytest.mark.parametrize("bits", [8, 16])
def test_raw_parts_are_read_only_within_read_px_of_the_windows(simulated_dataset, monkeypatch, bits):
    """The raw image's parts with every pixel beyond READ_PX of the windows poisoned (a checkerboard of 1 px
    of the darkest and brightest values): the detections and rejections in the windows are still the whole
    image's there, to the last bit (the image-wide numbers from the image itself). (Poisoned beyond 15 px of
    them, they are not.)"""
    root = simulated_dataset(FLIGHT)
    dataset = Dataset.load(root)
    rig = Rig.load(root / "truth" / "rig.json")
    image = dataset.read_image(dataset.images_of("flight")["image"].iloc[0])
    image = image.astype(np.uint16) * 257 if bits == 16 else image
    whole, rejected = detect(image, with_rejected=True)
    # Windows of 24 px about the detections (the priors' windows of 0.2 deg, ~137 px, hold all a marker's
    # reads): their tests and fits read well beyond them.
    uv = whole[["u", "v"]].to_numpy()
    boxes = np.vstack([np.column_stack([uv - 12.0, uv + 12.0]),
                       search_windows(_prediction_model(dataset, dataset.images_of("flight")["image"].iloc[0], rig),
                                      0.2)[:2]])
    members = windows.groups(boxes)
    poisoned = np.where((np.indices(image.shape).sum(axis=0) % 2).astype(bool), np.iinfo(image.dtype).max, 0
                        ).astype(image.dtype)
    for m in members:
        for x0, y0, x1, y1 in (windows._crop_bounds(image.shape, *b, windows.READ_PX) for b in m):
            poisoned[y0:y1, x0:x1] = image[y0:y1, x0:x1]
    made = windows._raw_parts
    monkeypatch.setattr(windows, "_raw_parts", lambda raw, groups: made(poisoned, groups))
    found, lost = detect_in_windows(image, boxes, with_rejected=True)
    pd.testing.assert_frame_equal(found, _in(whole, boxes), check_exact=True)
    pd.testing.assert_frame_equal(_sorted(lost), _sorted(_in(rejected, boxes)), check_exact=True)
    assert len(found) >= 3
