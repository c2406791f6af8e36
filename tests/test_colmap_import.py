"""`dmais intrinsics --import`: intrinsics from OpenCV calibration files and COLMAP cameras files."""

from __future__ import annotations

import re
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pycolmap
import pytest

from dmais_pipe import cli
from dmais_pipe.calib.import_intrinsics import (GRID_STEPS, ForeignCamera, convert_camera, one_coefficient_camera,
                                                read_colmap_cameras, read_opencv_file, write_opencv_file)
from dmais_pipe.calib.intrinsics import table_columns
from dmais_pipe.camera import Camera, project_unmasked
from dmais_pipe.calib.rig_ba import add_colmap_rig, colmap_camera
from dmais_pipe.colmap import FORMATS, MODEL_FILES, write_model
from dmais_pipe.dataset import write_dataset
from dmais_pipe.geometry import Rigid3
from dmais_pipe.errors import DmaisError
from dmais_pipe.stages import intrinsics
from dmais_pipe.workspace import Workspace

from conftest import observation_only

SIM = observation_only("colmap-import", seed=12, calib_images=3, eval_images=1, frames_per_group=1)


@pytest.fixture(scope="module")
def dataset(simulated_dataset):
    return simulated_dataset(SIM)


def _ours(dataset, name: str, d: float = -0.031) -> Camera:
    """A camera of the dataset's size with arbitrary, non-symmetric intrinsics."""
    spec = Workspace.open(dataset, dataset).dataset.cameras[name]
    return Camera(1.013 * spec.focal_px, 0.998 * spec.focal_px, spec.width / 2 + 3.25, spec.height / 2 - 7.5, d,
                  spec.width, spec.height)


@pytest.mark.parametrize("suffix", [".yaml", ".json"])
def test_ours_through_an_opencv_file_comes_back_unchanged(dataset, tmp_path, suffix):
    ours = _ours(dataset, "C1")
    source = write_opencv_file(ours, tmp_path / f"C1{suffix}")
    storage = cv2.FileStorage(str(source), cv2.FILE_STORAGE_READ)  # OpenCV's own reader sees our model
    np.testing.assert_array_equal(storage.getNode("camera_matrix").mat(), ours.K)
    np.testing.assert_array_equal(storage.getNode("distortion_coefficients").mat().ravel(), [ours.d, 0, 0, 0, 0])
    workspace = Workspace.open(dataset, tmp_path / "results")
    written = intrinsics.import_cameras(workspace, ["C1"], source)
    assert written == [workspace.intrinsics_path("C1"), workspace.methods_path("C1")]
    camera, record = workspace.load_intrinsics("C1")
    assert camera == ours
    assert record["method"] == f"imported from {source}"
    assert record["imported"]["residual_max_px"] < 1e-9  # OpenCV and our formula agree to rounding
    assert workspace.load_methods("C1")["method"].tolist() == ["imported"]


def test_a_colmap_cameras_file_imports_in_camera_id_order(dataset, tmp_path):
    ours = {"C0": _ours(dataset, "C0", -0.02), "C3": _ours(dataset, "C3", 0.015)}
    model = pycolmap.Reconstruction()
    for camera_id, camera in ((7, ours["C0"]), (9, ours["C3"])):
        model.add_camera(colmap_camera(camera, camera_id))
    model.write_text(tmp_path)
    workspace = Workspace.open(dataset, tmp_path / "results")
    intrinsics.import_cameras(workspace, ["C0", "C3"], tmp_path / "cameras.txt")
    for name, camera in ours.items():
        imported = workspace.load_intrinsics(name)[0]
        np.testing.assert_allclose([imported.fx, imported.fy, imported.cx, imported.cy, imported.d],
                                   [camera.fx, camera.fy, camera.cx, camera.cy, camera.d], rtol=0, atol=1e-12)
    # a hand-written SIMPLE_RADIAL line (COLMAP's pixel convention: the principal point - 0.5 is ours)
    spec = workspace.dataset.cameras["C2"]
    (tmp_path / "one" / "cameras.txt").parent.mkdir()
    (tmp_path / "one" / "cameras.txt").write_text(f"# Camera list\n1 SIMPLE_RADIAL {spec.width} {spec.height} "
                                                  f"{spec.focal_px} {spec.width / 2} {spec.height / 2} -0.05\n")
    intrinsics.import_cameras(workspace, ["C2"], tmp_path / "one" / "cameras.txt")
    assert workspace.load_intrinsics("C2")[0] == Camera(spec.focal_px, spec.focal_px, spec.width / 2 - 0.5,
                                                        spec.height / 2 - 0.5, -0.05, spec.width, spec.height)
    # another camera's file (focal far from the manifest's focal_px) is refused
    (tmp_path / "one" / "cameras.txt").write_text(f"1 SIMPLE_RADIAL {spec.width} {spec.height} 5000 2048 1500 0\n")
    with pytest.raises(DmaisError, match=r"camera C2: .* 89% from dataset.yaml's focal_px"):
        intrinsics.import_cameras(workspace, ["C2"], tmp_path / "one" / "cameras.txt")


def _foreign(dataset, **distortion) -> ForeignCamera:
    """A camera of C2's size with a wider field (focal ~ the image width) than the long-focal rig's, where
    k2 shows."""
    ours = _ours(dataset, "C2", 0.0)
    return ForeignCamera(ours.width, ours.width * 1.01, ours.cx, ours.cy, ours.width, ours.height, "test",
                         {"k1": -0.03, **distortion})


def test_a_k2_rich_model_is_refused_by_name(dataset):
    with pytest.raises(DmaisError, match=r"^camera C2: k2 = 0\.12 is not representable by the one-coefficient model"):
        one_coefficient_camera(_foreign(dataset, k2=0.12, p1=1e-5), "C2")


def test_a_converted_model_states_the_residual_it_leaves(dataset):
    foreign = _foreign(dataset, k2=0.001)
    conversion = one_coefficient_camera(foreign, "C2", max_residual_px=1.0)
    # the stated residual, recomputed with our Camera and OpenCV's projection on the same grid
    camera, K = conversion.camera, conversion.camera.K
    u, v = np.meshgrid(np.linspace(-0.5, camera.width - 0.5, GRID_STEPS),
                       np.linspace(-0.5, camera.height - 0.5, GRID_STEPS))
    xy = cv2.undistortPoints(np.column_stack([u.ravel(), v.ravel()]).reshape(-1, 1, 2), K,
                             foreign.coefficients()).reshape(-1, 2)
    rays = np.column_stack([xy, np.ones(len(xy))])
    theirs = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, foreign.coefficients())[0].reshape(-1, 2)
    residual = np.linalg.norm(camera.project(rays) - theirs, axis=1)
    assert conversion.residual_max_px == pytest.approx(residual.max(), rel=1e-9)
    assert conversion.residual_rms_px == pytest.approx(np.sqrt(np.mean(residual**2)), rel=1e-9)
    assert 0 < conversion.residual_max_px < 1.0
    # d is the least-squares optimum: a step either way, or k1 itself, leaves more
    for d in (camera.d - 1e-4, camera.d + 1e-4, -0.03):
        other = Camera(camera.fx, camera.fy, camera.cx, camera.cy, d, camera.width, camera.height)
        assert np.sum((other.project(rays) - theirs) ** 2) > np.sum(residual**2)
    with pytest.raises(DmaisError, match=r"camera C2: k2 = 0\.001 .* px max"):
        one_coefficient_camera(foreign, "C2", max_residual_px=0.5 * conversion.residual_max_px)


@pytest.mark.parametrize("name, content", [
    ("missing.yaml", None),
    ("corrupt.yaml", "%YAML:1.0\n---\ncamera_matrix: !!opencv-matrix\n   rows: 3\n   cols: [oops\n"),
    ("nomatrix.yaml", "%YAML:1.0\n---\nimage_width: 10\n"),
    ("cameras.txt", "1 OPENCV 640 480 not numbers\n"),
    ("cameras.bin", "garbage"),
])
def test_a_corrupt_or_missing_file_is_one_line_and_exit_2(dataset, tmp_path, capsys, name, content):
    if content is not None:
        (tmp_path / name).write_text(content)
    argv = ["intrinsics", str(dataset), "--out", str(tmp_path / "results"), "--camera", "C0",
            "--import", str(tmp_path / name)]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"dmais intrinsics: error: {tmp_path / name}") and err.count("\n") == 1, err
    assert not (tmp_path / "results" / "intrinsics").exists()


def test_a_size_mismatch_is_refused(dataset, tmp_path):
    ours = _ours(dataset, "C0")
    source = write_opencv_file(Camera(ours.fx, ours.fy, ours.cx, ours.cy, ours.d, ours.width + 2, ours.height),
                               tmp_path / "C0.yaml")
    assert read_opencv_file(source).width == ours.width + 2
    with pytest.raises(DmaisError, match=r"camera C0: .*C0.yaml is for \d+x\d+ images, dataset.yaml says"):
        intrinsics.import_cameras(Workspace.open(dataset, tmp_path / "results"), ["C0"], source)


def _stereo_file(path, cameras) -> None:
    """A stereo calibration file as OpenCV's stereo_calib sample writes it: M1, D1, M2, D2 (and R, T),
    no image size."""
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for n, camera in enumerate(cameras, start=1):
        storage.write(f"M{n}", camera.K)
        storage.write(f"D{n}", np.array([[camera.d, 0.0, 0.0, 0.0, 0.0]]))
    storage.write("R", np.eye(3))
    storage.write("T", np.array([[-0.1], [0.0], [0.0]]))
    storage.release()


def test_a_stereo_calibrations_pair_is_named_and_takes_the_datasets_size(dataset, tmp_path):
    left, right = _ours(dataset, "C0", -0.02), _ours(dataset, "C0", 0.012)
    right = Camera(right.fx * 1.004, right.fy * 1.003, right.cx - 11.0, right.cy + 6.0, right.d, right.width,
                   right.height)
    _stereo_file(tmp_path / "intrinsics.yml", [left, right])
    results = tmp_path / "results"
    argv = ["intrinsics", str(dataset), "--out", str(results), "--camera", "C0", "--import"]
    assert cli.main([*argv, f"{tmp_path / 'intrinsics.yml'}:M2"]) == 0
    camera, record = Workspace.open(dataset, results).load_intrinsics("C0")
    assert camera == right  # the size the dataset's, the file has none
    assert record["imported"]["model"] == "OpenCV stereo M2"
    assert record["imported"]["file"] == f"{tmp_path / 'intrinsics.yml'}:M2"
    intrinsics.import_cameras(Workspace.open(dataset, results), ["C0"], tmp_path / "intrinsics.yml:M1")
    assert Workspace.open(dataset, results).load_intrinsics("C0")[0] == left


@pytest.mark.parametrize("suffix, message", [
    ("", r"a stereo calibration \(M1, M2\); name the camera's pair, e.g. --import .*intrinsics.yml:M1"),
    (":M3", r"intrinsics.yml: missing matrix M3"),
])
def test_a_stereo_file_without_its_pair_is_one_line_and_exit_2(dataset, tmp_path, capsys, suffix, message):
    ours = _ours(dataset, "C0")
    _stereo_file(tmp_path / "intrinsics.yml", [ours, ours])
    argv = ["intrinsics", str(dataset), "--out", str(tmp_path / "results"), "--camera", "C0",
            "--import", f"{tmp_path / 'intrinsics.yml'}{suffix}"]
    assert cli.main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and re.search(message, err), err
    assert not (tmp_path / "results" / "intrinsics").exists()


# ------------------------------------------------------------------------------ opencv cameras

CHESSBOARD = Path(__file__).parent / "data" / "chessboard"  # OpenCV's stereo sample photographs, see its README.md
WIDE = (640, 480)  # their size
EXACT_PX = 1e-9


@pytest.fixture(scope="module")
def wide(tmp_path_factory):
    """A dataset of three cameras of the chessboard photographs' size and focal: W and V (model opencv), R
    (radial1); one observation each, which is all an import needs."""
    root = tmp_path_factory.mktemp("wide") / "dataset"
    spec = {"width": WIDE[0], "height": WIDE[1], "focal_px": 537.0}
    manifest = {"name": "wide", "reference_camera": "W",
                "cameras": {"W": {**spec, "model": "opencv"}, "V": {**spec, "model": "opencv"}, "R": spec}}
    points = pd.DataFrame({"point_id": ["A", "B", "C"], "x": [0.0, 1.0, 0.0], "y": [0.0, 0.0, 1.0], "z": 0.0})
    images = pd.DataFrame({"image": ["w", "v", "r"], "camera": ["W", "V", "R"], "stage": "intrinsics",
                           "split": "calib"})
    observations = pd.DataFrame({"image": ["w", "v", "r"], "point_id": "A", "u": 320.0, "v": 240.0})
    return write_dataset(root, manifest, points, images, observations=observations)


@pytest.fixture(scope="module")
def stereo() -> dict:
    """cv2.stereoCalibrate of eight pairs of OpenCV's stereo chessboard photographs, every coefficient of
    its default model free: a real wide-angle pair (f ~ 537 px, k1 ~ -0.28) with all five nonzero.
    Returns M1, D1, M2, D2 (D as (5,)), R, T."""
    gx, gy = np.meshgrid(np.arange(9), np.arange(6))
    board = (np.column_stack([gx.ravel(), gy.ravel(), np.zeros(gx.size)]) * 0.025).astype(np.float32)
    corners = {"left": [], "right": []}
    for k in range(1, 9):
        for side, found in corners.items():
            image = cv2.imread(str(CHESSBOARD / f"{side}0{k}.jpg"), cv2.IMREAD_GRAYSCALE)
            ok, points = cv2.findChessboardCorners(image, (9, 6))
            assert ok and image.shape == WIDE[::-1]
            found.append(cv2.cornerSubPix(image, points, (11, 11), (-1, -1),
                                          (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4)))
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-10)
    rms, M1, D1, M2, D2, R, T = cv2.stereoCalibrate([board] * 8, corners["left"], corners["right"], None, None, None,
                                                    None, WIDE, criteria=criteria, flags=0)[:7]
    assert rms < 1.0 and all(np.all(D.ravel() != 0) and -0.3 < D.ravel()[0] < -0.25 for D in (D1, D2))
    return {"M1": M1, "D1": D1.ravel(), "M2": M2, "D2": D2.ravel(), "R": R, "T": T}


def _opencv_camera(K, D) -> Camera:
    """Our opencv Camera of OpenCV's K (3, 3) and D (k1, k2, p1, p2[, k3]), of the photographs' size."""
    D = np.concatenate([np.ravel(D), np.zeros(5)])[:5]
    return Camera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], D[0], *WIDE, "opencv", *D[1:])


def _rays_over_the_image(K, D, steps: int = 41) -> np.ndarray:
    """(n, 3) rays whose pixels by OpenCV's model (K, D) are a steps x steps grid over the image, borders
    included (OpenCV's own iterative undistortion, run to convergence)."""
    u, v = np.meshgrid(np.linspace(-0.5, WIDE[0] - 0.5, steps), np.linspace(-0.5, WIDE[1] - 0.5, steps))
    criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-15)
    xy = cv2.undistortPoints(np.column_stack([u.ravel(), v.ravel()]).reshape(-1, 1, 2), K, np.ravel(D),
                             criteria=criteria).reshape(-1, 2)
    return np.column_stack([xy, np.ones(len(xy))])


def _opencv_pixels(rays, K, D) -> np.ndarray:
    return cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, np.ravel(D))[0].reshape(-1, 2)


def _calibration_file(path, K, D, size=WIDE):
    """An OpenCV calibration file as its calibration sample writes one."""
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    storage.write("image_width", size[0])
    storage.write("image_height", size[1])
    storage.write("camera_matrix", K)
    storage.write("distortion_coefficients", np.reshape(D, (-1, 1)))
    storage.release()
    return path


@pytest.mark.parametrize("length", [4, 5, 8, 14])
def test_an_opencv_file_imports_exactly_into_an_opencv_camera(wide, stereo, tmp_path, length):
    """A real lens's five coefficients (4: k3 left out; 8, 14: the rational, thin prism and tilt terms 0)."""
    K, D = stereo["M1"], np.concatenate([stereo["D1"], np.zeros(9)])[:length]
    workspace = Workspace.open(wide, tmp_path / "results")
    intrinsics.import_cameras(workspace, ["W"], _calibration_file(tmp_path / "W.yaml", K, D))
    camera, record = workspace.load_intrinsics("W")
    assert camera == _opencv_camera(K, D)  # the file's values, bit for bit
    rays = _rays_over_the_image(K, D)
    assert np.abs(camera.project(rays) - _opencv_pixels(rays, K, D)).max() <= EXACT_PX
    assert record["imported"]["residual_max_px"] <= EXACT_PX
    assert {k: record[k] for k in ("model", "k1", "k2", "p1", "p2", "k3")} == {
        "model": "opencv", **dict(zip(("k1", "k2", "p1", "p2", "k3"), camera.distortion))}
    methods = workspace.load_methods("W")
    assert list(methods.columns) == list(table_columns("opencv")) and methods["method"].tolist() == ["imported"]
    np.testing.assert_array_equal(methods.loc[0, list(camera.parameter_names)].to_numpy(float), camera.parameters)


@pytest.mark.parametrize("suffix", [".yaml", ".xml", ".json"])
def test_an_opencv_camera_through_an_opencv_file_comes_back_exactly(wide, stereo, tmp_path, suffix):
    ours = _opencv_camera(stereo["M2"], stereo["D2"])
    source = write_opencv_file(ours, tmp_path / f"W{suffix}")
    storage = cv2.FileStorage(str(source), cv2.FILE_STORAGE_READ)  # OpenCV's own reader sees the whole model
    np.testing.assert_array_equal(storage.getNode("camera_matrix").mat(), ours.K)
    np.testing.assert_array_equal(storage.getNode("distortion_coefficients").mat().ravel(), ours.distortion)
    workspace = Workspace.open(wide, tmp_path / "results")
    intrinsics.import_cameras(workspace, ["W"], source)
    camera = workspace.load_intrinsics("W")[0]
    assert camera == ours
    rays = _rays_over_the_image(ours.K, ours.distortion)
    assert np.abs(camera.project(rays) - ours.project(rays)).max() <= EXACT_PX


def _stereo_calibration_file(path, stereo) -> Path:
    """The file OpenCV's stereo_calib sample writes: M1, D1, M2, D2 (1 x 5), R, T; no image size."""
    storage = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for key in ("M1", "D1", "M2", "D2", "R", "T"):
        storage.write(key, stereo[key][None, :] if key[0] == "D" else stereo[key])
    storage.release()
    return path


def test_a_wide_angle_stereo_calibration_imports_exactly_into_an_opencv_camera(wide, stereo, tmp_path, capsys):
    source = _stereo_calibration_file(tmp_path / "intrinsics.yml", stereo)
    results = tmp_path / "results"
    argv = ["intrinsics", str(wide), "--out", str(results), "--import"]
    assert cli.main([*argv, f"{source}:M2", "--camera", "W"]) == 0
    camera = Workspace.open(wide, results).load_intrinsics("W")[0]
    assert camera == _opencv_camera(stereo["M2"], stereo["D2"])
    rays = _rays_over_the_image(stereo["M2"], stereo["D2"])
    assert np.abs(camera.project(rays) - _opencv_pixels(rays, stereo["M2"], stereo["D2"])).max() <= EXACT_PX
    # the same lens into the radial1 camera: refused by its k2, the largest term radial1 lacks
    capsys.readouterr()
    assert cli.main([*argv, f"{source}:M1", "--camera", "R"]) == 2
    err = capsys.readouterr().err
    k2 = stereo["D1"][1]
    assert err.count("\n") == 1 and f"camera R: k2 = {k2:.6g} is not representable by the one-coefficient model" in err
    assert not Workspace.open(wide, results).intrinsics_path("R").exists()


@pytest.mark.parametrize("fmt", FORMATS)
def test_opencv_cameras_through_a_colmap_model_come_back_exactly(wide, stereo, tmp_path, fmt):
    """W (k3 != 0) is exported as FULL_OPENCV, V (k3 = 0) as OPENCV; both are read back and imported exactly, and
    COLMAP's own projection of each is ours + 0.5 px."""
    ours = {"W": _opencv_camera(stereo["M1"], stereo["D1"]), "V": _opencv_camera(stereo["M2"], stereo["D2"][:4])}
    model = pycolmap.Reconstruction()
    add_colmap_rig(model, ours, ["W", "V"], {"W": Rigid3.identity(), "V": Rigid3(np.eye(3), stereo["T"].ravel())})
    write_model(model, tmp_path / fmt, fmt)
    cameras_file = tmp_path / fmt / MODEL_FILES[fmt][0]
    read = read_colmap_cameras(cameras_file)
    assert [read[1].model, read[2].model] == ["COLMAP FULL_OPENCV", "COLMAP OPENCV"]
    workspace = Workspace.open(wide, tmp_path / "results")
    intrinsics.import_cameras(workspace, ["W", "V"], cameras_file)
    colmap = pycolmap.Reconstruction(tmp_path / fmt).cameras  # COLMAP's reading of the files
    for camera_id, (name, camera) in enumerate(ours.items(), start=1):
        imported, record = workspace.load_intrinsics(name)
        np.testing.assert_allclose(imported.parameters, camera.parameters, rtol=1e-15, atol=1e-13)
        assert record["imported"]["residual_max_px"] <= EXACT_PX
        rays = _rays_over_the_image(camera.K, camera.distortion)
        pixels = camera.project(rays)
        assert np.abs(imported.project(rays) - pixels).max() <= EXACT_PX
        assert np.abs(colmap[camera_id].img_from_cam(rays) - (pixels + 0.5)).max() <= EXACT_PX


@pytest.mark.parametrize("extra, fitted", [({"k4": 0.01}, True), ({"k6": 0.01}, True), ({"s1": 0.003}, False),
                                           ({"tau_x": 0.01}, False)])
def test_a_richer_model_is_fitted_with_its_residual_or_refused_by_name(stereo, extra, fitted):
    """Rational terms that move the image corners by pixels are absorbed into k1, k2, k3 (0.0006 and 0.02 px
    left); thin prism and tilt terms of that size are not (0.56 and 0.91 px), and are named."""
    K, D = stereo["M1"], stereo["D1"]
    foreign = ForeignCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], *WIDE, "test",
                            {**dict(zip(("k1", "k2", "p1", "p2", "k3"), D)), **extra})
    coefficients = foreign.coefficients()
    grid_rays = _grid_rays(foreign)
    theirs = _opencv_pixels(grid_rays, K, coefficients)
    assert np.abs(theirs - _opencv_pixels(grid_rays, K, D)).max() > 0.5  # the extra term matters
    if not fitted:
        (name, value), = extra.items()
        with pytest.raises(DmaisError, match=rf"^camera W: {name} = {value:g} is not representable by the opencv "
                                             r"model \(k1, k2, p1, p2, k3\): the best k1 = .* px max"):
            convert_camera(foreign, "W", "opencv")
        return
    conversion = convert_camera(foreign, "W", "opencv")
    camera = conversion.camera
    residual = np.linalg.norm(camera.project(grid_rays) - theirs, axis=1)  # restated with our Camera
    assert conversion.residual_max_px == pytest.approx(residual.max(), rel=1e-6)
    assert conversion.residual_rms_px == pytest.approx(np.sqrt(np.mean(residual**2)), rel=1e-6)
    assert 0 < conversion.residual_max_px < 0.1
    # the least-squares optimum: a step in any coefficient, or the file's own five, leave more
    for k in range(4, 9):
        for step in (-1e-5, 1e-5):
            other = camera.with_parameters(camera.parameters + step * (np.arange(9) == k))
            assert np.sum((project_unmasked(grid_rays, other) - theirs) ** 2) > np.sum(residual**2)
    assert np.sum((_opencv_camera(K, D).project(grid_rays) - theirs) ** 2) > np.sum(residual**2)
    with pytest.raises(DmaisError, match=rf"camera W: {next(iter(extra))} = 0\.01 is not representable"):
        convert_camera(foreign, "W", "opencv", max_residual_px=0.5 * conversion.residual_max_px)


def _grid_rays(foreign: ForeignCamera) -> np.ndarray:
    """The rays of the conversion's grid (GRID_STEPS x GRID_STEPS pixels over the image, undistorted by
    OpenCV as the conversion does)."""
    K = np.array([[foreign.fx, 0.0, foreign.cx], [0.0, foreign.fy, foreign.cy], [0.0, 0.0, 1.0]])
    u, v = np.meshgrid(np.linspace(-0.5, foreign.width - 0.5, GRID_STEPS),
                       np.linspace(-0.5, foreign.height - 0.5, GRID_STEPS))
    xy = cv2.undistortPoints(np.column_stack([u.ravel(), v.ravel()]).reshape(-1, 1, 2), K,
                             foreign.coefficients()).reshape(-1, 2)
    return np.column_stack([xy, np.ones(len(xy))])


def test_an_opencv_model_that_folds_inside_the_central_half_of_the_image_is_refused(wide, stereo, tmp_path):
    """k1 alone, exact, but so strong that r (1 + k1 r^2) turns at a third of the image's half-diagonal
    (k1 = -1.5: one-to-one over 29% of the image): refused for an opencv camera; a radial1 camera takes
    it (the paper's model is not checked, as `calib.intrinsics.Plausibility` says)."""
    source = _calibration_file(tmp_path / "W.yaml", stereo["M1"], [-1.5, 0.0, 0.0, 0.0, 0.0])
    with pytest.raises(DmaisError, match=r"^camera W: the imported opencv model folds back inside the central part of "
                                         r"the image \(one-to-one within 16\d px of the principal point, 2\d\.\d% of "
                                         r"the image .*at least 50% needed\); not a lens calibration$"):
        intrinsics.import_cameras(Workspace.open(wide, tmp_path / "results"), ["W"], source)
    assert not (tmp_path / "results" / "intrinsics").exists()
    intrinsics.import_cameras(Workspace.open(wide, tmp_path / "results"), ["R"], source)
    assert Workspace.open(wide, tmp_path / "results").load_intrinsics("R")[0].folds_in_image


def test_an_opencv_model_that_folds_near_the_corners_is_imported_with_its_region(wide, stereo, tmp_path, caplog):
    """k1 = -0.6 turns at undistorted radius 0.745, distorted 0.497 (266 px at f = 536), short of the
    image's corners: imported with a warning giving the region, which the record keeps; its pixels
    beyond undistort to NaN, those within round-trip."""
    source = _calibration_file(tmp_path / "W.yaml", stereo["M1"], [-0.6, 0.0, 0.0, 0.0, 0.0])
    with caplog.at_level("WARNING"):
        intrinsics.import_cameras(Workspace.open(wide, tmp_path / "results"), ["W"], source)
    camera, record = Workspace.open(wide, tmp_path / "results").load_intrinsics("W")
    region = record["one_to_one"]
    assert region["undistorted_radius"] == pytest.approx(1 / np.sqrt(1.8), rel=1e-6)
    f = min(camera.fx, camera.fy)
    assert region["radius_px"] == pytest.approx(2 / 3 * f / np.sqrt(1.8), rel=2e-3)  # r (1 + k1 r^2) at the turn
    assert 0.6 < region["image_fraction"] < 0.8
    assert f"{region['image_fraction']:.1%} of the image" in caplog.text and "camera W: the imported" in caplog.text
    corners = np.array([[-0.5, -0.5], [camera.width - 0.5, camera.height - 0.5]])
    assert np.isnan(camera.undistort(corners)).all()
    inside = np.array([[camera.cx + 0.9 * region["radius_px"], camera.cy], [camera.cx, camera.cy - 200.0]])
    assert np.allclose(camera.distort(camera.undistort(inside)), inside, atol=1e-6)
