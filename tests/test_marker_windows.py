"""Markers searched in windows about the priors' predictions: exactly what the whole image gives there."""

from __future__ import annotations

import copy
import shutil

import numpy as np
import pandas as pd
import pytest
import yaml

from dmais_pipe.dataset import Dataset
from dmais_pipe.errors import DmaisError
from dmais_pipe.markers.detect import detect
from dmais_pipe.markers.extract import _prediction_model, predicted_projections, process_image, search_windows
from dmais_pipe.markers.windows import detect_in_windows
from dmais_pipe.rig import Rig
from dmais_pipe.sim.config import DEFAULTS
from dmais_pipe.stages import markers
from dmais_pipe.workspace import Workspace

SCALE = 0.25  # the paper's rig at 1024 x 768 px: the same fields of view, 2 m markers of ~65 px


def _small_rig() -> dict:
    rig = copy.deepcopy(DEFAULTS["rig"])
    rig["width"], rig["height"] = int(rig["width"] * SCALE), int(rig["height"] * SCALE)
    rig["nominal_focal_px"] *= SCALE
    for entry in rig["cameras"].values():
        for key in ("fx", "fy", "cx", "cy"):
            entry[key] *= SCALE
    return rig


#: One rendered frame of the five cameras; an INS of 0.02 deg without boresight (the windows' test
#: bound below is 0.2 deg), the calibration stages observation-only.
FLIGHT = {
    "name": "windows",
    "seed": 4040,
    "rig": _small_rig(),
    "render": {"intrinsics": False, "extrinsics": False, "flight": True},
    "intrinsics": {"calib_images_per_camera": 3, "eval_images_per_camera": 0},
    "flight": {"sites": {"A": {"center_m": [1500.0, -800.0, 45.0], "groups": [1]}}, "frames_per_group": 1,
               "ins_attitude_sigma_deg": 0.02, "ins_boresight_deg": [0.0, 0.0, 0.0]},
}
BOUND_DEG = 0.2
QUAT = ["prior_qw", "prior_qx", "prior_qy", "prior_qz"]


@pytest.fixture(scope="module")
def flight(simulated_dataset):
    root = simulated_dataset(FLIGHT)
    dataset = Dataset.load(root)
    return root, dataset, Rig.load(root / "truth" / "rig.json")


def _in(frame: pd.DataFrame, boxes: np.ndarray) -> pd.DataFrame:
    uv = frame[["u", "v"]].to_numpy(dtype=float)
    inside = ((uv[:, None] >= boxes[None, :, :2]) & (uv[:, None] <= boxes[None, :, 2:])).all(axis=2).any(axis=1)
    return frame[inside].reset_index(drop=True)


def _sorted(rejected: pd.DataFrame) -> pd.DataFrame:
    return rejected.sort_values(["v", "u", "reason"], ignore_index=True)


def _flight_images(dataset: Dataset) -> list[str]:
    return dataset.images_of("flight")["image"].tolist()


def test_detection_in_windows_is_the_whole_image_s_there_8_and_16_bit(flight):
    """Windows of every size, at the image's borders, overlapping, on 8- and 16-bit pixels: the same
    detections and rejections (compared as sets) to the last bit."""
    _, dataset, _ = flight
    image = dataset.read_image(_flight_images(dataset)[0])
    height, width = image.shape
    whole, rejected = detect(image, with_rejected=True)
    assert len(whole) >= 4
    uv = whole[["u", "v"]].to_numpy()
    boxes = np.vstack([np.column_stack([uv[:3] - r, uv[:3] + r]) for r in (6.0, 40.0, 150.0)]
                      + [[-0.5, -0.5, 200.0, 150.0], [width - 300.0, height - 90.0, width - 0.5, height - 0.5],
                         [uv[3, 0] - 10.0, uv[3, 1] - 10.0, uv[3, 0] + 300.0, uv[3, 1] + 12.0]])
    for pixels in (image, image.astype(np.uint16) * 257):
        found, lost = detect_in_windows(pixels, boxes, with_rejected=True)
        full, full_lost = detect(pixels, with_rejected=True)
        pd.testing.assert_frame_equal(found, _in(full, boxes), check_exact=True)
        pd.testing.assert_frame_equal(_sorted(lost), _sorted(_in(full_lost, boxes)), check_exact=True)
        assert len(found) >= 3


def test_flight_images_windowed_equal_the_whole_image(flight):
    """With priors, the windows about the predictions give every id of the whole image's search at the
    same position, and the whole image's detections within the windows."""
    _, dataset, rig = flight
    identified = 0
    for image in _flight_images(dataset):
        phases = {}
        windowed = process_image(dataset, image, rig, attitude_deg=BOUND_DEG, seconds=phases)
        whole = process_image(dataset, image, rig, attitude_deg=None)
        assert phases["windows"] > 0 and phases["whole_image"] == 0, image
        boxes = search_windows(_prediction_model(dataset, image, rig), BOUND_DEG)
        pd.testing.assert_frame_equal(windowed, _in(whole, boxes), check_exact=True)
        named = whole[whole["point_id"] != ""].reset_index(drop=True)
        pd.testing.assert_frame_equal(windowed[windowed["point_id"] != ""].reset_index(drop=True), named)
        identified += len(named)
    assert identified >= 20


def _copy(root, tmp_path, frames_edit):
    """The dataset at `root` copied to tmp_path with frames.csv changed by frames_edit(frames)."""
    copied = shutil.copytree(root, tmp_path / "data")
    frames = pd.read_csv(copied / "frames.csv", dtype={"frame": str, "group": str}, keep_default_na=False)
    frames_edit(frames)
    frames.to_csv(copied / "frames.csv", index=False)
    return Dataset.load(copied)


def test_a_prior_beyond_its_bound_falls_back_to_the_whole_image(flight, tmp_path):
    """An INS 1.5 deg off (the bound 0.2 deg): nothing in the windows is identified, the whole image is
    searched, and its result is the whole image's."""
    root, _, rig = flight

    def turned(frames):
        q = frames[QUAT].to_numpy(dtype=float)
        from scipy.spatial.transform import Rotation
        off = Rotation.from_rotvec(np.radians([1.0, -1.1, 0.3])) * Rotation.from_quat(q[:, [1, 2, 3, 0]])
        frames[QUAT] = off.as_quat()[:, [3, 0, 1, 2]]

    dataset = _copy(root, tmp_path, turned)
    image = _flight_images(dataset)[0]
    phases = {}
    found = process_image(dataset, image, rig, attitude_deg=BOUND_DEG, seconds=phases)
    assert phases["windows"] > 0 and phases["whole_image"] == 1
    pd.testing.assert_frame_equal(found, process_image(dataset, image, rig, attitude_deg=None), check_exact=True)
    assert (found["point_id"] != "").sum() >= 4


def test_without_priors_the_whole_image_is_searched(flight, tmp_path):
    root, _, rig = flight

    def no_attitude(frames):
        frames[QUAT] = ""

    dataset = _copy(root, tmp_path, no_attitude)
    image = _flight_images(dataset)[0]
    phases = {}
    found = process_image(dataset, image, rig, attitude_deg=BOUND_DEG, seconds=phases)
    assert phases["windows"] == 0 and phases["whole_image"] == 1
    assert (found["point_id"] == "").all() and len(found) >= 4
    pd.testing.assert_frame_equal(found[["u", "v", "score", "sigma_px", "fit_residual"]],
                                  detect(dataset.read_image(image)), check_exact=True)


def test_a_part_of_windows_far_apart_is_read_only_about_them(flight, monkeypatch):
    """Windows far apart in one part (their parts would overlap): only the pixels READ_PX about a window
    are converted, and no test or fit reads the rest of the part. With the rest NaN, the detections
    and rejections are still the whole image's in the windows, to the last bit."""
    from dmais_pipe.markers import rings, windows

    _, dataset, _ = flight
    image = dataset.read_image(_flight_images(dataset)[0])
    whole, rejected = detect(image, with_rejected=True)
    uv = whole[["u", "v"]].to_numpy()
    # Windows about detections ~400-600 px apart merge into one part whose box holds much that none reads.
    picks = [0]
    for k in range(1, len(uv)):
        if all(np.hypot(*(uv[k] - uv[j])) > 300.0 for j in picks):
            picks.append(k)
    boxes = np.column_stack([uv[picks] - 12.0, uv[picks] + 12.0])
    members = windows.groups(boxes)
    assert max(len(m) for m in members) >= 2
    made = windows._parts(image, members)
    lone = sum(w * h for w, h in zip(made.widths, made.heights))
    union = sum((x1 - x0) * (y1 - y0) for m in members
                for x0, y0, x1, y1 in windows._union([windows._crop_bounds(image.shape, *b, windows.READ_PX) for b in m]))
    assert union < 0.95 * lone  # the parts' boxes hold pixels no window reads
    empty = np.empty

    def poisoned(shape, dtype=float, *args, **kwargs):  # the parts' buffer: NaN where not converted
        out = empty(shape, dtype, *args, **kwargs)
        out.fill(np.nan)
        return out

    monkeypatch.setattr(rings.np, "empty", poisoned)
    parts = windows._parts(image, members)
    monkeypatch.undo()
    for pixels, top, left, m in zip(parts.pixels, parts.tops, parts.lefts, members):
        for x0, y0, x1, y1 in (windows._crop_bounds(image.shape, *b, windows.READ_PX) for b in m):
            np.testing.assert_array_equal(pixels[y0 - top:y1 - top, x0 - left:x1 - left], image[y0:y1, x0:x1])
        assert np.isnan(pixels).any() or len(m) == 1
    monkeypatch.setattr(windows, "_parts", lambda raw, groups: parts)
    found, lost = detect_in_windows(image, boxes, with_rejected=True)
    pd.testing.assert_frame_equal(found, _in(whole, boxes), check_exact=True)
    pd.testing.assert_frame_equal(_sorted(lost), _sorted(_in(rejected, boxes)), check_exact=True)
    assert len(found) >= 3


def test_a_given_pos_lever_arm_puts_the_predictions_at_the_rig_s_centre(flight, tmp_path):
    """frames.csv's POS is the rig's centre plus its lever arm turned into the world, plus the POS's
    noise (2-3 cm): with the lever arm given, the predictions are the true centre's to that noise; not
    given (0.37 m) or reversed, they are further off. The windows of a POS-sized position bound then
    find every id of the whole image."""
    root, dataset, rig = flight
    lever = np.array(yaml.safe_load((root / "truth" / "simulation.yaml").read_text())["flight"]["lever_arm_m"])
    truth = pd.read_csv(root / "truth" / "frames.csv", dtype={"frame": str}).set_index("frame")

    def at_the_centre(frames):
        frames[["pos_x", "pos_y", "pos_z"]] = truth.loc[frames["frame"], ["x", "y", "z"]].to_numpy()

    centred = _copy(root, tmp_path, at_the_centre)
    for image in _flight_images(dataset):
        exact = predicted_projections(centred, image, rig)[0]
        off = {name: np.abs(predicted_projections(dataset, image, rig, lever_arm=arm)[0] - exact).max()
               for name, arm in (("given", lever), ("none", None), ("reversed", -lever))}
        assert off["given"] < 0.3 * off["none"] < 0.3 * off["reversed"], (image, off)
        phases = {}
        windowed = process_image(dataset, image, rig, attitude_deg=BOUND_DEG, position_m=0.1, lever_arm=lever,
                                 seconds=phases)
        assert phases["windows"] > 0 and phases["whole_image"] == 0, image
        whole = process_image(dataset, image, rig, attitude_deg=None)
        named = whole[whole["point_id"] != ""].reset_index(drop=True)
        pd.testing.assert_frame_equal(windowed[windowed["point_id"] != ""].reset_index(drop=True), named)


@pytest.mark.parametrize("arm", [("0.1", "0.2"), ("0", "0", "x"), ("0", "nan", "0")])
def test_a_pos_lever_arm_that_is_not_three_numbers_stops_the_markers_stage(flight, tmp_path, arm):
    root, _, _ = flight
    workspace = Workspace.open(root, tmp_path)
    with pytest.raises(DmaisError, match="markers: setting pos_lever_arm: .* is not three numbers"):
        markers.run(workspace, markers.Conf(pos_lever_arm=arm))
    assert not any(tmp_path.rglob("*.csv"))  # stopped before any image
