"""The intrinsic calibration with OpenCV's lens model (k1, k2, p1, p2, k3): synthetic truth, the
`dmais intrinsics` files of such a camera, and OpenCV's own calibration of real photographs."""

from __future__ import annotations

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml
from scipy.spatial.transform import Rotation

from dmais_pipe.bench import periodic
from dmais_pipe.calib.intrinsics import (Plausibility, calibrate_camera, check_plausible, evaluate, table_columns)
from dmais_pipe.camera import Camera
from dmais_pipe.dataset import write_dataset
from dmais_pipe.errors import DmaisError
from dmais_pipe.geometry import Rigid3
from dmais_pipe.stages import intrinsics
from dmais_pipe.workspace import Workspace

# cv2.calibrateCamera's result on OpenCV's left*.jpg sample, rounded: a wide-angle lens, one-to-one over its image.
WIDE = Camera(532.8, 532.9, 342.5, 233.9, -0.281, 640, 480, "opencv", k2=0.0252, p1=0.0012, p2=-0.00018, k3=0.16)
# A strong barrel lens whose model folds inside the image (k3 < 0 turns it back before the corners).
FOLDING = Camera(420.0, 420.0, 319.5, 239.5, -0.30, 640, 480, "opencv", k2=0.05, p1=0.001, p2=0.0, k3=-0.05)
# The paper's kind of camera: one radial coefficient.
RADIAL = Camera(505.0, 502.0, 317.5, 243.0, -0.12, 640, 480)


def field_views(camera: Camera, n_views: int, rng: np.random.Generator, noise: float = 0.1, field=None):
    """A 3-D field (P, 3) (default: 150 random points in a 3 x 2 x 1.5 m box) seen from 2.2-3.5 m,
    turned by up to 0.45 rad about each axis: the field and per view {image: (rows of the field
    (n,), pixels (n, 2) with Gaussian noise)} of the points it images at least 2 px inside the border."""
    if field is None:
        field = rng.uniform([-1.5, -1.0, -0.75], [1.5, 1.0, 0.75], size=(150, 3))
    views = {}
    while len(views) < n_views:
        pose = Rigid3(Rotation.from_euler("xyz", rng.uniform(-0.45, 0.45, 3)).as_matrix(),
                      np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), rng.uniform(2.2, 3.5)]))
        uv = camera.project(pose.apply(field))
        seen = np.flatnonzero(np.isfinite(uv).all(axis=1) & camera.in_image(np.nan_to_num(uv, nan=-1e9), margin=2))
        if len(seen) >= 40:
            views[f"view{len(views)}"] = (seen, uv[seen] + rng.normal(scale=noise, size=(len(seen), 2)))
    return field, views


def split_views(field: np.ndarray, views: dict, n_eval: int = 0):
    """calibrate_camera's arguments of `views`: (calib points, calib pixels, eval points, eval pixels),
    the last n_eval views held out."""
    names = list(views)
    calib, held = names[:len(names) - n_eval], names[len(names) - n_eval:]
    return ({k: field[views[k][0]] for k in calib}, {k: views[k][1] for k in calib},
            {k: field[views[k][0]] for k in held}, {k: views[k][1] for k in held})


# ------------------------------------------------------------------------------ synthetic truth


def test_a_seeded_field_recovers_the_true_opencv_camera_within_its_reported_sigmas():
    """0.1 px noise: each of the nine parameters within 4 of its reported sigmas of the truth, the
    sigmas themselves small (the field determines every coefficient), eps about the noise's."""
    rng = np.random.default_rng(30)
    field, views = field_views(WIDE, 10, rng)
    X, uv, eX, euv = split_views(field, views, n_eval=2)
    result = calibrate_camera(X, uv, 640, 480, eval_points_world_per_image=eX, eval_uv_per_image=euv,
                              name="wide", model="opencv")
    assert result.camera.model == "opencv" and set(result.std) == set(WIDE.parameter_names)
    for name, value, truth in zip(WIDE.parameter_names, result.camera.parameters, WIDE.parameters):
        assert abs(value - truth) < 4 * result.std[name], (name, value, truth, result.std[name])
    assert max(result.std[k] for k in ("fx", "fy", "cx", "cy")) < 0.5
    assert max(result.std[k] for k in ("k1", "k2", "k3")) < 0.01 and max(result.std[k] for k in ("p1", "p2")) < 1e-4
    # 0.1 px per axis: the RMS point distance is 0.1 * sqrt(2) = 0.14 px (less the fitted parameters' share)
    assert 0.12 < result.eps_calib_px < 0.15 and 0.12 < result.eps_eval_px < 0.16


def test_noise_free_observations_give_the_opencv_camera_exactly():
    rng = np.random.default_rng(31)
    field, views = field_views(WIDE, 5, rng, noise=0.0)
    X, uv, _, _ = split_views(field, views)
    result = calibrate_camera(X, uv, 640, 480, model="opencv")
    error = np.abs(result.camera.parameters - WIDE.parameters)
    assert np.all(error <= [1e-8, 1e-8, 1e-8, 1e-8, 1e-10, 1e-10, 1e-12, 1e-12, 1e-10]), error
    assert result.eps_calib_px < 1e-7


def test_the_radial1_model_cannot_fit_an_opencv_lens():
    """The same observations with the paper's one coefficient leave the lens' k2, k3 and tangential
    terms in the residuals: the model is what the fit above measured, not the noise."""
    rng = np.random.default_rng(30)
    field, views = field_views(WIDE, 10, rng)
    X, uv, _, _ = split_views(field, views)
    radial1 = calibrate_camera(X, uv, 640, 480, model="radial1")
    opencv = calibrate_camera(X, uv, 640, 480, model="opencv")
    assert radial1.camera.model == "radial1" and set(radial1.std) == {"fx", "fy", "cx", "cy", "d"}
    assert radial1.eps_calib_px > 3 * opencv.eps_calib_px


def test_a_calibration_that_folds_inside_the_image_is_refused_naming_the_camera():
    rng = np.random.default_rng(32)
    field, views = field_views(FOLDING, 6, rng)
    X, uv, _, _ = split_views(field, views)
    result = calibrate_camera(X, uv, 640, 480, name="fisheye", model="opencv")
    assert result.eps_calib_px < 0.2 and result.camera.folds_in_image  # a good fit of a lens model that folds
    with pytest.raises(DmaisError, match=r"^camera fisheye: calibration refused, its opencv distortion \(k1 -0\.\d+ "
                                         r"k2 .*\) folds back inside the image .*earlier results are kept$"):
        check_plausible(result, 420.0, Plausibility())
    good = calibrate_camera(*split_views(*field_views(WIDE, 4, rng))[:2], 640, 480, name="wide", model="opencv")
    check_plausible(good, 535.0, Plausibility())


# ------------------------------------------------------------------------------ the stage's files


def write_field_dataset(root, cameras: dict[str, tuple[Camera, str]], seed: int):
    """A dataset of 6 calib and 2 eval views of a 3-D field per camera (name -> (truth, dataset.yaml
    model)), the observations given (no image files)."""
    rng = np.random.default_rng(seed)
    field = rng.uniform([-1.5, -1.0, -0.75], [1.5, 1.0, 0.75], size=(150, 3))
    images, observations = [], []
    for name, (camera, _) in cameras.items():
        _, views = field_views(camera, 8, rng, field=field)
        for k, (image, (rows, uv)) in enumerate(views.items()):
            images.append({"image": f"{name}_{image}", "camera": name, "stage": "intrinsics",
                           "split": "calib" if k < 6 else "eval", "path": ""})
            observations.append(pd.DataFrame({"image": f"{name}_{image}", "point_id": [f"p{r}" for r in rows],
                                              "u": uv[:, 0], "v": uv[:, 1]}))
    points = pd.DataFrame(field, columns=["x", "y", "z"], index=pd.Index([f"p{k}" for k in range(len(field))],
                                                                        name="point_id"))
    manifest = {"name": "field", "reference_camera": next(iter(cameras)),
                "cameras": {name: {"width": c.width, "height": c.height, "focal_px": c.fx, "model": model}
                            for name, (c, model) in cameras.items()}}
    write_dataset(root, manifest, points, pd.DataFrame(images), observations=pd.concat(observations))
    return root


def test_the_stage_writes_each_cameras_model_and_a_table_of_both(tmp_path):
    """One opencv and one radial1 camera: each JSON reads back as the camera calibrated with its model
    (Camera.from_dict), each methods file has its model's columns, the table the union; the OpenCV
    baseline (its default model) and dlt_lm reach our optimum."""
    dataset = write_field_dataset(tmp_path / "dataset", {"W": (WIDE, "opencv"), "R": (RADIAL, "radial1")}, seed=5)
    workspace = Workspace.open(dataset, tmp_path / "results")
    intrinsics.run(workspace)
    camera, record = workspace.load_intrinsics("W")
    assert camera.model == "opencv" and record["model"] == "opencv" and set(record["std"]) == set(WIDE.parameter_names)
    assert "d" not in record and list(record)[:13] == ["camera", "model", "width", "height", *WIDE.parameter_names]
    for name, value, truth in zip(WIDE.parameter_names, camera.parameters, WIDE.parameters):
        assert abs(value - truth) < 4 * record["std"][name], name
    radial, radial_record = workspace.load_intrinsics("R")
    assert radial.model == "radial1" and "model" not in radial_record and abs(radial.d - RADIAL.d) < 0.01
    methods = workspace.load_methods("W").set_index("method")
    assert list(workspace.load_methods("W").columns) == list(table_columns("opencv"))
    assert list(workspace.load_methods("R").columns) == list(table_columns("radial1"))
    for method in ("opencv", "dlt_lm"):
        for name in WIDE.parameter_names:
            assert methods.loc[method, name] == pytest.approx(methods.loc["ours", name],
                                                              abs=0.05 * record["std"][name]), (method, name)
        assert methods.loc[method, "eps_eval_px"] == pytest.approx(methods.loc["ours", "eps_eval_px"], rel=1e-4)
    table = pd.read_csv(tmp_path / "results" / "tables" / "intrinsics.csv")
    assert list(table.columns) == ["method", "camera", "fx", "fy", "cx", "cy", "d", "k1", "k2", "p1", "p2", "k3",
                                   "eps_calib_px", "eps_eval_px"]
    rows = table.set_index(["method", "camera"])
    assert rows.loc[("ours", "W"), "k3"] == pytest.approx(camera.k3) and np.isnan(rows.loc[("ours", "W"), "d"])
    assert rows.loc[("ours", "R"), "d"] == pytest.approx(radial.d) and np.isnan(rows.loc[("ours", "R"), "k1"])


def test_a_methods_file_of_another_model_is_named_before_the_table_mixes_them(tmp_path):
    dataset = write_field_dataset(tmp_path / "dataset", {"W": (WIDE, "opencv")}, seed=6)
    results = tmp_path / "results"
    intrinsics.run_cameras(Workspace.open(dataset, results), ["W"], intrinsics.CONFS["ours"])
    manifest = yaml.safe_load((dataset / "dataset.yaml").read_text())
    del manifest["cameras"]["W"]["model"]
    (dataset / "dataset.yaml").write_text(yaml.safe_dump(manifest))
    with pytest.raises(DmaisError, match=r"W\.methods\.csv has the columns method, camera, fx, fy, cx, cy, k1, .*"
                                         r"not those of camera W's model radial1 .*dmais intrinsics --camera W"):
        intrinsics.write_table(Workspace.open(dataset, results))


def test_the_stage_refuses_a_folding_calibration_and_keeps_the_earlier_result(tmp_path):
    """The FOLDING lens' views of seed 8 reach its fold (rays beyond 90% of its radius; those of seed 7
    stop short of it, and that calibration would be accepted with its one-to-one region)."""
    dataset = write_field_dataset(tmp_path / "dataset", {"W": (WIDE, "opencv")}, seed=7)
    results = tmp_path / "results"
    intrinsics.run_cameras(Workspace.open(dataset, results), ["W"], intrinsics.CONFS["ours"])
    written = {p.name: p.read_bytes() for p in (results / "intrinsics").iterdir()}
    folding = write_field_dataset(tmp_path / "folding", {"W": (FOLDING, "opencv")}, seed=8)
    for name in ("dataset.yaml", "observations.csv", "control_points.csv"):
        (dataset / name).write_bytes((folding / name).read_bytes())
    with pytest.raises(DmaisError, match=r"^camera W: calibration refused, its opencv distortion .* folds back inside "
                                         r"the image .*\(worst images: W_view"):
        intrinsics.run_cameras(Workspace.open(dataset, results), ["W"], intrinsics.CONFS["ours"])
    assert {p.name: p.read_bytes() for p in (results / "intrinsics").iterdir()} == written


# ------------------------------------------------------------------------------ real photographs


@pytest.fixture(scope="module")
def photographs():
    return periodic.photographs(periodic.PHOTOS)


@pytest.fixture(scope="module")
def calibrated_photographs(photographs, tmp_path_factory):
    """`dmais intrinsics` (conf ours) of the chessboard photographs' dataset with `model: opencv`, the
    true corners (findChessboardCorners + cornerSubPix) as its observations."""
    root = tmp_path_factory.mktemp("chessboard")
    periodic.write_photo_dataset(photographs, root / "dataset", seed=0, model="opencv", corners=True)
    workspace = Workspace.open(root / "dataset", root / "results")
    intrinsics.run_cameras(workspace, ["left", "right"], intrinsics.CONFS["ours"])
    return workspace


def opencv_reference(photographs: dict, side: str) -> tuple[Camera, dict, float, float]:
    """cv2.calibrateCamera (its default model, default flags) on the side's calib split: the camera,
    its standard deviations, its eps_calib (the RMS per-point distance it returns) and its eps_eval
    (the held-out images' poses alone fitted with its intrinsics, as ours)."""
    def split(name):
        photos = [p for p in photographs.values() if p["camera"] == side and p["split"] == name]
        return [periodic.board_points()] * len(photos), [p["corners"] for p in photos]

    (X, uv), (eX, euv) = split("calib"), split("eval")
    rms, K, dist, _, _, std, _, _ = cv2.calibrateCameraExtended(
        [x.astype(np.float32) for x in X], [c.astype(np.float32) for c in uv], (640, 480), None, None)
    camera = Camera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], 0.0, 640, 480, "opencv").with_parameters(
        [K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist.ravel()[:5]])
    return camera, dict(zip(camera.parameter_names, std.ravel()[:9])), rms, evaluate(camera, eX, euv, side)


@pytest.mark.parametrize("side", ["left", "right"])
def test_real_photographs_give_opencvs_own_calibration(photographs, calibrated_photographs, side):
    """OpenCV's stereo sample (640 x 480, k1 ~ -0.27): ours and cv2.calibrateCamera with the same
    model, split and corners agree to 0.1% in focal length, 1 px in principal point, eps_eval within
    0.005 px. Measured: every parameter within 4e-5 of OpenCV's standard deviations (so 1e-3 here),
    those within 6e-7 of ours, both eps_eval within 6e-7 (eps_calib 3e-7: OpenCV's returned RMS is
    that much below the RMS of its own solution's float64 reprojections, which equals ours)."""
    camera, record = calibrated_photographs.load_intrinsics(side)
    theirs, theirs_std, theirs_eps_calib, theirs_eps_eval = opencv_reference(photographs, side)
    assert camera.model == "opencv" and record["n_images"] == 11 and record["n_eval_images"] == 2
    assert -0.3 < theirs.d < -0.25 and 500 < theirs.fx < 560  # a real wide-angle lens, not a degenerate fit
    assert abs(camera.fx / theirs.fx - 1) < 1e-3 and abs(camera.fy / theirs.fy - 1) < 1e-3
    assert np.hypot(camera.cx - theirs.cx, camera.cy - theirs.cy) < 1.0
    assert record["eps_eval_px"] <= theirs_eps_eval + 0.005
    for name, ours, value in zip(camera.parameter_names, camera.parameters, theirs.parameters):
        assert abs(ours - value) < 1e-3 * theirs_std[name], (name, ours, value, theirs_std[name])
        assert record["std"][name] == pytest.approx(theirs_std[name], rel=1e-4), name
    assert record["eps_calib_px"] == pytest.approx(theirs_eps_calib, rel=1e-5)
    assert record["eps_eval_px"] == pytest.approx(theirs_eps_eval, rel=1e-5)
    assert not camera.folds_in_image
