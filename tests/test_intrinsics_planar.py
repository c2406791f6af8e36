"""A flat calibration board (issue 42, item 4): the intrinsics start from the views' homographies, as
cv2.calibrateCamera's do, and reach its calibration; the rig of the views the cameras share is
cv2.stereoCalibrate's and the truth's. Seeded boards of 88 points (an asymmetric circle grid) with
half of each camera's views 1-4 deg from parallel to the image plane, 0.15 px noise."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from dmais_pipe import cli
from dmais_pipe.calib import intrinsics as calib_intrinsics
from dmais_pipe.calib.intrinsics import calibrate_camera, evaluate
from dmais_pipe.calib.planar import planar_start, plane_frame
from dmais_pipe.camera import Camera, image_centre
from dmais_pipe.errors import DmaisError
from dmais_pipe.geometry import Rigid3, rotation_angle
from dmais_pipe.sim.board import (RIG_CAM_FROM_RIG, RIG_CAMERAS, BoardScene, BoardView, asymmetric_circle_grid,
                                  board_pose, board_scene, write_board_dataset)
from dmais_pipe.stages import extrinsics, intrinsics
from dmais_pipe.workspace import Workspace

SEED = 4201


@pytest.fixture(scope="module")
def scene():
    return board_scene(RIG_CAMERAS, RIG_CAM_FROM_RIG, views_per_camera=16, placements=8, seed=SEED)


def camera_split(scene, camera: str, n_eval: int = 3):
    """(calib points, calib pixels, eval points, eval pixels) of a camera's views, the last n_eval held out."""
    names = [k for k, v in scene.views.items() if v.camera == camera]
    calib, held = names[:-n_eval], names[-n_eval:]
    return ({k: scene.points for k in calib}, {k: scene.views[k].pixels for k in calib},
            {k: scene.points for k in held}, {k: scene.views[k].pixels for k in held})


def opencv_reference(scene, camera: Camera, X: dict, uv: dict, eX: dict, euv: dict) -> tuple[Camera, float]:
    """cv2.calibrateCamera (default flags: its own planar start, the opencv model) on the calib views and
    its eps_eval (the held-out views' poses alone fitted, as ours)."""
    _, K, dist, _, _ = cv2.calibrateCamera([X[k].astype(np.float32) for k in X], [uv[k].astype(np.float32) for k in X],
                                           (camera.width, camera.height), None, None)
    theirs = camera.with_parameters([K[0, 0], K[1, 1], K[0, 2], K[1, 2], *dist.ravel()[:5]])
    return theirs, evaluate(theirs, eX, euv)


def test_the_papers_pnpf_start_refuses_this_board(scene):
    """The data is the issue's case: the PnPf focal lengths of the near-fronto-parallel views scatter
    and today's start stops."""
    X, uv, _, _ = camera_split(scene, "C0")
    views = {k: (X[k], uv[k]) for k in X}
    with pytest.raises(DmaisError, match=r"^camera C0: the PnPf focal lengths disagree"):
        calib_intrinsics._pnpf_start(views, image_centre(1920, 1080), "C0")


@pytest.mark.parametrize("name", ["C0", "C2"])
def test_a_board_calibrates_as_cv2_calibrateCamera(scene, name):
    """fx, fy within 0.1% of cv2.calibrateCamera's, the principal point within 1 px, eps_eval within
    0.005 px (measured: 1e-7 relative, 1e-4 px); every parameter within 4 reported sigmas of the truth."""
    truth = RIG_CAMERAS[name]
    X, uv, eX, euv = camera_split(scene, name)
    ours = calibrate_camera(X, uv, truth.width, truth.height, eval_points_world_per_image=eX, eval_uv_per_image=euv,
                            name=name, model="opencv")
    theirs, theirs_eps_eval = opencv_reference(scene, truth, X, uv, eX, euv)
    assert abs(ours.camera.fx / theirs.fx - 1) < 1e-3 and abs(ours.camera.fy / theirs.fy - 1) < 1e-3
    assert np.hypot(ours.camera.cx - theirs.cx, ours.camera.cy - theirs.cy) < 1.0
    assert abs(ours.eps_eval_px - theirs_eps_eval) < 0.005
    for parameter, value, true in zip(truth.parameter_names, ours.camera.parameters, truth.parameters):
        assert abs(value - true) < 4 * ours.std[parameter], (parameter, value, true, ours.std[parameter])
    assert 0.17 < ours.eps_calib_px < 0.23  # 0.15 px per axis: 0.21 px per point


def test_the_planar_start_is_exact_for_a_pinhole_camera():
    """Noise-free views of a pinhole camera: the start's focal length and each view's tilt are the truth."""
    pinhole = Camera(1400.0, 1400.0, 959.5, 539.5, 0.0, 1920, 1080, "opencv")
    scene = board_scene({"P": pinhole}, {"P": Rigid3.identity()}, views_per_camera=8, placements=0, seed=SEED,
                        noise_px=0.0)
    start = planar_start({k: (scene.points, v.pixels) for k, v in scene.views.items()}, image_centre(1920, 1080), "P")
    assert start.focal_px == pytest.approx(1400.0, rel=1e-6) and start.relative_std < 1e-6
    for image, view in scene.views.items():
        assert start.tilt_deg[image] == pytest.approx(np.degrees(np.arccos(view.cam_from_world.R[2, 2])), abs=1e-4)


def test_the_planar_start_weighs_fronto_parallel_views_out(scene):
    """Each view's weight in the focal length's start grows with its perspective: the views 1-4 deg
    from the image plane carry under 5% of it together (a homography's fit of the strong barrel
    distortion gives them a little perspective), the tilted ones the rest; the start lies within
    25% of the truth (the distortion's share; the LM takes it out)."""
    truth = RIG_CAMERAS["C0"]
    X, uv, _, _ = camera_split(scene, "C0")
    start = planar_start({k: (X[k], uv[k]) for k in X}, image_centre(1920, 1080), "C0")
    assert abs(start.focal_px / truth.fx - 1) < 0.25
    true_tilt = {k: np.degrees(np.arccos(abs(scene.views[k].cam_from_world.R[2, 2]))) for k in X}
    fronto = [k for k in X if true_tilt[k] < 5.0]
    assert len(fronto) >= len(X) / 2 - 1 and sum(start.weight[k] for k in fronto) < 0.05
    assert sum(start.weight.values()) == pytest.approx(1.0)


def untilted_scene(n_views: int, seed: int) -> BoardScene:
    """C2's views of the board, each exactly parallel to the image plane, 0.15 px noise."""
    camera, rng = RIG_CAMERAS["C2"], np.random.default_rng(seed)
    scene = BoardScene(asymmetric_circle_grid(), {"C2": camera}, {"C2": Rigid3.identity()})
    for k in range(n_views):
        pose = board_pose(camera, scene.points, 0.0, rng)
        uv = camera.project(pose.apply(scene.points))
        scene.views[f"C2_v{k:02d}"] = BoardView("C2", "", pose, uv + rng.normal(scale=0.15, size=uv.shape))
    return scene


def test_a_board_never_tilted_is_refused_in_one_line():
    """Every view parallel to the image plane: no perspective, no focal length; the refusal names the camera
    and the views' tilts."""
    scene = untilted_scene(6, SEED)
    views = {k: (scene.points, v.pixels) for k, v in scene.views.items()}
    with pytest.raises(DmaisError, match=r"^camera C2: the 6 views of its flat calibration field do not determine the "
                                         r"focal length \(their perspective fixes it not at all: .*: C2_v00, C2_v01, "):
        planar_start(views, image_centre(1280, 720), "C2")


def test_a_tilted_plane_in_the_world_is_a_plane():
    rng = np.random.default_rng(SEED)
    turned = Rigid3(cv2.Rodrigues(rng.normal(size=3))[0], rng.normal(size=3)).apply(asymmetric_circle_grid())
    centre, axes = plane_frame(turned)
    assert np.allclose((turned - centre) @ np.cross(*axes), 0.0, atol=1e-12)
    bent = turned.copy()
    bent[0] += 0.01 * np.cross(*axes)  # one point 1 cm off a 15 cm board
    assert plane_frame(bent) is None


def test_the_stages_calibrate_a_board_rig_as_stereoCalibrate(scene, tmp_path):
    """`dmais intrinsics` and `dmais extrinsics` (no priors) on the board's dataset: each camera's
    intrinsics are OpenCV's baseline's (its own planar start), and cam_from_rig of each camera sharing
    views with C0 is cv2.stereoCalibrate's with the same intrinsics over the placements they share
    (measured 0.001 deg, 0.01 mm) and the truth's (0.04 deg, 0.3 mm: the intrinsics' errors)."""
    dataset = write_board_dataset(scene, tmp_path / "dataset")
    workspace = Workspace.open(dataset, tmp_path / "results")
    intrinsics.run(workspace, intrinsics.Conf(methods=("ours", "opencv")))
    for name in RIG_CAMERAS:
        methods = workspace.load_methods(name).set_index("method")
        assert methods.loc["opencv", "fx"] == pytest.approx(methods.loc["ours", "fx"], rel=1e-6)
    extrinsics.run(workspace, extrinsics.CONFS["no_priors"])
    rig = json.loads((tmp_path / "results" / "rig.json").read_text())
    ours = {c["name"]: Rigid3(np.array(c["cam_from_rig"]["R"]), np.array(c["cam_from_rig"]["t"])) for c in rig["cameras"]}
    cameras = {name: workspace.load_intrinsics(name)[0] for name in RIG_CAMERAS}
    for name in ("C1", "C2"):
        reference = stereo_calibrate(scene, cameras["C0"], cameras[name], name)
        assert np.degrees(rotation_angle(ours[name].R @ reference.R.T)) < 0.005
        assert np.linalg.norm(ours[name].t - reference.t) < 5e-5
        assert np.degrees(rotation_angle(ours[name].R @ RIG_CAM_FROM_RIG[name].R.T)) < 0.1
        assert np.linalg.norm(ours[name].t - RIG_CAM_FROM_RIG[name].t) < 1e-3


def stereo_calibrate(scene, first: Camera, second: Camera, name: str) -> Rigid3:
    """second_from_first by cv2.stereoCalibrate with both cameras' intrinsics fixed, over the placements
    where both see the board."""
    placements = sorted({v.placement for v in scene.views.values() if v.placement and v.camera == name}
                        & {v.placement for v in scene.views.values() if v.placement and v.camera == "C0"})
    first_pixels = [scene.views[f"C0_{p}"].pixels.astype(np.float32) for p in placements]
    second_pixels = [scene.views[f"{name}_{p}"].pixels.astype(np.float32) for p in placements]
    result = cv2.stereoCalibrate([scene.points.astype(np.float32)] * len(placements), first_pixels, second_pixels,
                                 first.K, np.array(first.distortion), second.K, np.array(second.distortion),
                                 (first.width, first.height), flags=cv2.CALIB_FIX_INTRINSIC,
                                 criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12))
    return Rigid3(result[5], result[6].ravel())


def test_dmais_intrinsics_on_a_board_never_tilted_is_one_line_and_exit_2(tmp_path, capsys):
    """The stage's refusal of such a board: one line naming the camera, exit 2, nothing written."""
    dataset = write_board_dataset(untilted_scene(6, SEED + 1), tmp_path / "dataset", eval_views=1)
    assert cli.main(["intrinsics", str(dataset), "--out", str(tmp_path / "results")]) == 2
    err = capsys.readouterr().err
    assert err.startswith("dmais intrinsics: error: camera C2: the 5 views of its flat calibration field do not "
                          "determine the focal length") and err.count("\n") == 1, err
    assert not (tmp_path / "results" / "intrinsics").exists()
