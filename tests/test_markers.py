"""Marker extraction: sub-pixel refinement, detection and identification on renders with known truth."""

from __future__ import annotations

import cv2
import numpy as np
import pandas as pd
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from dmais_pipe.camera import Camera
from dmais_pipe.dataset import Dataset, write_dataset
from dmais_pipe.errors import DatasetError, DmaisError
from dmais_pipe.files import write_png_atomic
from dmais_pipe.geometry import Rigid3
from dmais_pipe.markers import detect, identify, refine
from dmais_pipe.markers.centring import seed as coarse_centre
from dmais_pipe.markers.extract import verify_with_pose
from dmais_pipe.markers.rings import CLEAN_BLOCK_RINGS, ImageParts, as_float_image, clean_radius
from dmais_pipe.stages import intrinsics, markers as markers_stage
from dmais_pipe.sim.render import MarkerBoard, RenderSettings, render_image
from dmais_pipe.workspace import Workspace

SMALL = Camera(2000.0, 2000.0, 319.7, 239.4, 0.0, 640, 480)
FULL = Camera(45000.0, 45000.0, 2051.2, 1497.6, 3.0, 4096, 3000)
POSE = Rigid3(Rotation.from_euler("zyx", [0.7, -0.4, 2.1]).as_matrix(), [12.0, -30.0, 250.0]).inverse()
NOISY = RenderSettings()  # the simulator's defaults: texture, blur 0.8 px, vignetting, noise


def board_at(camera, cam_from_world, pixel, distance, *, roll=0.0, tilt=0.0, tilt_axis=0.0, cols=2, rows=2,
             cell=1.0, polarity=1, margin=0.0) -> MarkerBoard:
    """A board whose centre projects to `pixel`, `distance` m along the ray, rolled and tilted."""
    bearing = camera.unproject(np.asarray(pixel, dtype=float))[0]
    u = np.cross([0.0, 1.0, 0.0], bearing)
    u /= np.linalg.norm(u)
    v = np.cross(bearing, u)
    R = (Rotation.from_rotvec(tilt * (np.cos(tilt_axis) * u + np.sin(tilt_axis) * v))
         * Rotation.from_rotvec(roll * bearing)).as_matrix()
    world_from_cam = cam_from_world.inverse()
    return MarkerBoard(world_from_cam.apply(bearing * distance), world_from_cam.R @ (R @ u),
                       world_from_cam.R @ (R @ v), cols, rows, cell, cell, polarity, margin)


def corners_of(camera, boards) -> np.ndarray:
    return np.concatenate([camera.project(POSE.apply(b.corners())) for b in boards])


def offsets(n, rng, max_px=1.5) -> np.ndarray:
    angle = rng.uniform(0, 2 * np.pi, n)
    radius = rng.uniform(0.3, max_px, n)
    return radius[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])


def corner_sub_pix(image, start, half=11) -> np.ndarray:
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    points = np.asarray(start, dtype=np.float32).reshape(-1, 1, 2).copy()
    return cv2.cornerSubPix(image, points, (half, half), (-1, -1), criteria).reshape(-1, 2).astype(float)


def rms(error) -> float:
    return float(np.sqrt(np.mean(np.sum(np.asarray(error) ** 2, axis=1))))


# Six ~100-200 px markers on a 640 x 480 image: rotations, 30-60 deg foreshortening, both polarities.
SMALL_CASES = [  # pixel, distance, roll, tilt deg, tilt axis, polarity
    ((120.0, 110.0), 22.0, 0.0, 0.0, 0.0, 1),
    ((320.0, 110.0), 25.0, 0.5, 60.0, 0.3, -1),
    ((520.0, 120.0), 24.0, 1.1, 45.0, 1.9, 1),
    ((120.0, 350.0), 20.0, -0.7, 55.0, -1.0, -1),
    ((330.0, 360.0), 30.0, 0.25, 30.0, 2.5, 1),
    ((530.0, 350.0), 26.0, -0.2, 50.0, 0.8, -1),
]


def small_scene(seed: int, settings=NOISY):
    boards = [board_at(SMALL, POSE, p, d, roll=r, tilt=np.radians(t), tilt_axis=a, polarity=s)
              for p, d, r, t, a, s in SMALL_CASES]
    return boards, render_image(SMALL, POSE, boards, np.random.default_rng(seed), settings)


@pytest.fixture(scope="module")
def small_scenes():
    return [small_scene(seed) for seed in range(8)]


# ------------------------------------------------------------------------------ refine


def test_refine_accuracy_and_versus_corner_sub_pix(small_scenes):
    rng = np.random.default_rng(0)
    ours, theirs = [], []
    for boards, image in small_scenes:
        truth = corners_of(SMALL, boards)
        start = truth + offsets(len(truth), rng)
        ours.append(refine(image, start) - truth)
        theirs.append(corner_sub_pix(image, start) - truth)
    ours, theirs = np.concatenate(ours), np.concatenate(theirs)
    assert np.all(np.isfinite(ours))
    assert rms(ours) < 0.05
    assert rms(ours) <= rms(theirs)


def test_refine_full_size_image():
    boards = [board_at(FULL, POSE, p, 450.0, roll=r, tilt=np.radians(t), tilt_axis=a, polarity=s)
              for p, r, t, a, s in [((3850.0, 2800.0), 0.0, 0.0, 0.0, 1), ((250.0, 200.0), 0.4, 60, 0.3, -1),
                                    ((2048.0, 1500.0), 0.25, 30, 2.5, -1)]]
    boards.append(board_at(FULL, POSE, (3300.0, 1000.0), 450.0, roll=0.3, tilt=np.radians(40), tilt_axis=0.5,
                           cols=4, rows=3, cell=0.5, margin=0.15))
    image = render_image(FULL, POSE, boards, np.random.default_rng(7), NOISY)
    truth = corners_of(FULL, boards)
    found = refine(image, truth + offsets(len(truth), np.random.default_rng(1), 2.0))
    np.testing.assert_array_less(np.linalg.norm(found - truth, axis=1), 0.1)
    assert rms(found - truth) < 0.05
    # detection of the same image: every X-corner, no board outline corner, nothing else
    detections = detect(image)
    assert len(detections) == len(truth)
    distance, _ = cKDTree(truth).query(detections[["u", "v"]].to_numpy())
    assert distance.max() < 0.15


def test_refine_fails_cleanly_on_flat_and_edge():
    image = np.full((100, 100), 120, np.uint8)
    image[:, 50:] = 200  # one straight edge: no corner
    out = refine(image, [[20.0, 20.0], [50.0, 50.0], [-30.0, 10.0]])
    assert out.shape == (3, 2) and np.isnan(out).all()
    assert refine(image, np.zeros((0, 2))).shape == (0, 2)


def test_ring_tests_and_centring_give_each_point_what_it_gets_alone(small_scenes):
    """`clean_radius` (several rings per call where the points are few, one where they are more than
    CLEAN_BLOCK_RINGS) and `seed` (its window's gradients gathered once for all steps) give each point
    what it gets alone, and the same on a one-part `rings.ImageParts` (indexed directly) as on the
    float image: the windowed search's detections stay the whole image's to the last bit."""
    boards, image = small_scenes[0]
    img = as_float_image(image)
    rng = np.random.default_rng(3)
    truth = corners_of(SMALL, boards)
    points = np.vstack([truth, truth + rng.normal(0.0, 1.0, truth.shape),
                        rng.uniform([-5.0, -5.0], [645.0, 485.0], (CLEAN_BLOCK_RINGS + 50, 2))])
    clean_alone = np.array([clean_radius(img, point[None])[0] for point in points])
    seed_alone = np.vstack([coarse_centre(img, point[None], 3.0) for point in points])
    part = ImageParts([(0, 0, img.shape[1], img.shape[0])], img.shape)
    part.pixels[0][...] = img
    for pixels in (img, part):
        assert np.array_equal(clean_radius(pixels, points), clean_alone)
        assert np.array_equal(clean_radius(pixels, points[:len(truth)]), clean_alone[:len(truth)])
        assert np.array_equal(coarse_centre(pixels, points, 3.0), seed_alone, equal_nan=True)
    assert clean_alone[:len(truth)].min() >= 30.0  # the markers' rings reach past the first block of rings
    assert np.isnan(seed_alone).any() and np.isfinite(seed_alone).any()


def chessboard_photo(square=24, cols=9, rows=7, angle=17.0, blur=1.2, noise=2.0, seed=0):
    """An ordinary (synthetic) photograph of a chessboard: drawn large, rotated, blurred, noisy, 8-bit."""
    scale = 8
    board = np.kron((np.indices((rows, cols)).sum(0) % 2).astype(np.float32), np.ones((square * scale,) * 2, np.float32))
    canvas = np.full(((rows + 4) * square * scale, (cols + 4) * square * scale), 1.0, np.float32)
    canvas[2 * square * scale:(rows + 2) * square * scale, 2 * square * scale:(cols + 2) * square * scale] = board
    h, w = canvas.shape
    # similarity: rotate about the centre and shrink by `scale`; pixel centres handled exactly
    a = np.radians(angle)
    c = np.array([(w - 1) / 2, (h - 1) / 2])
    out_size = (w // scale, h // scale)
    M = np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) / scale
    t = np.array([(out_size[0] - 1) / 2, (out_size[1] - 1) / 2]) - M @ c
    warp = np.hstack([M, t[:, None]])
    # area average: blur at the large scale first, then sample
    canvas = cv2.GaussianBlur(canvas, (0, 0), 0.5 * scale)
    image = cv2.warpAffine(canvas, warp, out_size, flags=cv2.INTER_LINEAR, borderValue=1.0)
    image = cv2.GaussianBlur(image, (0, 0), blur) * 170 + 40
    image += np.random.default_rng(seed).normal(0, noise, image.shape)
    ij = np.stack(np.meshgrid(np.arange(1, cols), np.arange(1, rows)), -1).reshape(-1, 2)
    corners_big = (ij + 2) * square * scale - 0.5  # pixel-corner positions in the big canvas
    truth = corners_big @ M.T + t
    return np.clip(image + 0.5, 0, 255).astype(np.uint8), truth


def test_refine_and_detect_ordinary_chessboard():
    image, truth = chessboard_photo()
    rng = np.random.default_rng(3)
    found = refine(image, truth + offsets(len(truth), rng))
    assert rms(found - truth) < 0.05
    detections = detect(image)
    assert len(detections) == len(truth)  # inner corners only: outer L-corners and T-junctions rejected
    distance, _ = cKDTree(truth).query(detections[["u", "v"]].to_numpy())
    assert distance.max() < 0.1


# ------------------------------------------------------------------------------ detect


def check_detections(image, truth, tolerance=0.2):
    frame = detect(image)
    assert list(frame.columns) == ["u", "v", "score", "sigma_px", "fit_residual"]
    found = frame[["u", "v"]].to_numpy()
    assert len(found) == len(truth), (found, truth)
    distance, index = cKDTree(found).query(truth)
    assert distance.max() < tolerance and len(set(index)) == len(truth)
    return frame


def test_detect_recall_and_precision(small_scenes):
    for boards, image in small_scenes[:4]:
        frame = check_detections(image, corners_of(SMALL, boards))
        assert frame["score"].between(0, 1).all()


def test_detect_16_bit():
    boards, image = small_scene(11)
    check_detections(image.astype(np.uint16) * 257, corners_of(SMALL, boards))


@pytest.mark.parametrize("blur, noise", [(2.0, 1.5), (0.8, 5.0)])
def test_detect_blur_and_noise(blur, noise):
    settings = RenderSettings(blur_sigma_px=blur, read_noise_dn=noise)
    boards, image = small_scene(5, settings)
    check_detections(image, corners_of(SMALL, boards), tolerance=0.3)


def test_detect_small_markers_multi_board_and_border():
    """~20-40 px markers (60 deg foreshortened too), a 4 x 3 board with margin (6 X-corners,
    outline and T-junctions rejected), X-corners 8-12 px from the image border."""
    boards = [
        board_at(SMALL, POSE, (100.0, 100.0), 200.0),  # 20 px
        board_at(SMALL, POSE, (200.0, 100.0), 120.0, roll=0.6, tilt=np.radians(60), polarity=-1),  # 33 x 17 px
        board_at(SMALL, POSE, (300.0, 110.0), 150.0, roll=1.0, polarity=-1),  # 27 px
        board_at(SMALL, POSE, (420.0, 300.0), 30.0, roll=0.3, tilt=np.radians(30), cols=4, rows=3, cell=0.5,
                 margin=0.15),
        board_at(SMALL, POSE, (10.0, 300.0), 40.0, roll=0.2),  # corner 10 px from the left border
        board_at(SMALL, POSE, (600.0, 471.0), 40.0, roll=-0.3, polarity=-1),  # 9 px from the bottom
    ]
    image = render_image(SMALL, POSE, boards, np.random.default_rng(2), NOISY)
    check_detections(image, corners_of(SMALL, boards), tolerance=0.3)


def test_detect_empty_and_texture_only():
    for image in (np.zeros((480, 640), np.uint8), np.full((3, 3), 7, np.uint8)):
        frame = detect(image)
        assert frame.empty and list(frame.columns) == ["u", "v", "score", "sigma_px", "fit_residual"]
    for seed in range(3):  # fractal texture, rougher and stronger than the default
        settings = RenderSettings(background_contrast=40.0, background_roughness=0.2)
        texture = render_image(SMALL, POSE, [], np.random.default_rng(seed), settings)
        assert detect(texture).empty


# ------------------------------------------------------------------------------ identify


def perturbed(pose: Rigid3, degrees: float, rng) -> Rigid3:
    axis = rng.normal(size=3)
    R = Rotation.from_rotvec(np.radians(degrees) * axis / np.linalg.norm(axis)).as_matrix() @ pose.R
    centre = pose.center + rng.normal(0, 0.02, 3)
    return Rigid3(R, -R @ centre)


def field(rng, n=40):
    """Control points scattered in front of a camera at the origin looking along +z, 130-280 m."""
    z = rng.uniform(130, 280, n)
    x = rng.uniform(-0.06, 0.06, n) * z
    y = rng.uniform(-0.045, 0.045, n) * z
    return np.column_stack([x, y, z])


def test_identify_with_2_degree_prior_gives_only_correct_ids():
    camera = Camera(44300.0, 44350.0, 2060.0, 1490.0, 2.5, 4096, 3000)
    nominal = Camera(45000.0, 45000.0, 2047.5, 1499.5, 0.0, 4096, 3000)
    total = wrong = correct = 0
    for seed in range(12):
        rng = np.random.default_rng(seed)
        points = field(rng)
        ids = np.array([f"P{k:03d}" for k in range(len(points))], dtype=object)
        truth_pose = Rigid3.identity()
        uv = camera.project(truth_pose.apply(points))
        seen = camera.in_image(uv, margin=-20)
        detections = uv[seen] + rng.normal(0, 0.05, (seen.sum(), 2))
        detections = np.vstack([detections, rng.uniform([0, 0], [4096, 3000], (2, 2))])  # 2 unknown markers
        prior = perturbed(truth_pose, 2.0, rng)
        predicted = nominal.project(prior.apply(points))
        got = identify(detections, predicted, ids, (4096, 3000))
        expected = np.concatenate([ids[seen], ["", ""]])
        total += seen.sum()
        wrong += np.count_nonzero((got != "") & (got != expected))
        correct += np.count_nonzero((got != "") & (got == expected))
    assert wrong == 0
    assert correct >= 0.9 * total


def test_identify_refuses_without_enough_structure():
    rng = np.random.default_rng(1)
    det = rng.uniform(0, 1000, (3, 2))
    assert list(identify(det, det + 5, ["a", "b", "c"])) == ["", "", ""]
    assert list(identify(np.zeros((0, 2)), det, ["a", "b", "c"])) == []
    # a regular grid shifted by exactly one step is ambiguous: nothing is identified wrongly
    grid = np.stack(np.meshgrid(np.arange(6) * 700.0, np.arange(4) * 700.0), -1).reshape(-1, 2) + 300
    ids = np.array([f"G{k}" for k in range(len(grid))], dtype=object)
    got = identify(grid[:12], grid + [700.0, 0.0], ids)
    assert all(g == "" or g == i for g, i in zip(got, ids[:12]))


def test_identify_leaves_unnamed_a_detection_beside_a_nearer_rejected_corner():
    """A shadow edge along a small marker's stem: its corner rejected (with a reason), a "virtual"
    X 8 px off where the edge crosses the outline detected. The prediction, nearer the rejected
    corner, must not name the virtual X; a rejection farther than the detection changes nothing."""
    rng = np.random.default_rng(3)
    truth = rng.uniform([100, 100], [3900, 2900], (8, 2))
    ids = np.array([f"M{k}" for k in range(len(truth))], dtype=object)
    detections = truth + rng.normal(0, 0.05, truth.shape)
    detections[2] = truth[2] + [-8.0, 0.3]
    predicted = truth + [35.0, -20.0]
    assert identify(detections, predicted, ids, (4096, 3000))[2] == "M2"  # the wrong id this guards against
    got = identify(detections, predicted, ids, (4096, 3000), rejected=truth[[2]] + [0.7, 0.2])
    assert list(got) == [i if k != 2 else "" for k, i in enumerate(ids)]
    farther = identify(detections, predicted, ids, (4096, 3000), rejected=truth[[2]] + [-20.0, 0.0])
    assert list(farther) == list(ids)


# ------------------------------------------------------------------------------ stage


def small_dataset(root, seed=0):
    """Two intrinsic images rendered with a 640 x 480 camera and 1-deg priors, one hand-measured image."""
    rng = np.random.default_rng(seed)
    boards, poses, rows = [], [], []
    world = []
    for k in range(12):
        pixel = (60 + (k % 4) * 170 + rng.uniform(-20, 20), 60 + (k // 4) * 170 + rng.uniform(-20, 20))
        board = board_at(SMALL, Rigid3.identity(), pixel, rng.uniform(40, 70), roll=rng.uniform(-1, 1),
                         tilt=np.radians(rng.uniform(0, 40)), tilt_axis=rng.uniform(0, 3), polarity=1 - 2 * (k % 2))
        boards.append(board)
        world.append(board.corners()[0])
    control = pd.DataFrame(world, columns=["x", "y", "z"], index=pd.Index([f"L{k:02d}" for k in range(12)],
                                                                          name="point_id"))
    for k in range(2):
        pose = perturbed(Rigid3.identity(), 0.3, rng)  # true pose near identity
        image = render_image(SMALL, pose, boards, rng, NOISY)
        write_png_atomic(root / "images" / f"i{k}.png", image)
        prior = perturbed(pose, 1.0, rng)
        q = prior.quat
        c = pose.center + rng.normal(0, 0.02, 3)
        rows.append({"image": f"i{k}", "camera": "C0", "stage": "intrinsics", "split": "calib", "path": f"images/i{k}.png",
                     "prior_x": c[0], "prior_y": c[1], "prior_z": c[2],
                     "prior_qw": q[0], "prior_qx": q[1], "prior_qy": q[2], "prior_qz": q[3]})
        poses.append(pose)
    rows.append({"image": "hand", "camera": "C0", "stage": "intrinsics", "split": "eval", "path": ""})
    manifest = {"name": "t", "reference_camera": "C0", "cameras": {"C0": {"width": 640, "height": 480, "focal_px": 2000.0}}}
    observations = pd.DataFrame({"image": ["hand"], "point_id": ["L03"], "u": [100.5], "v": [200.25]})
    write_dataset(root, manifest, control, pd.DataFrame(rows), observations=observations)
    return poses, control


def test_markers_stage_writes_results(tmp_path):
    poses, control = small_dataset(tmp_path / "data")
    out = markers_stage.run(Workspace.open(tmp_path / "data", tmp_path / "results"))[-1]
    assert out == tmp_path / "results" / "observations.csv"
    observations = pd.read_csv(out, dtype={"point_id": str, "image": str}, keep_default_na=False)
    assert list(observations.columns) == ["image", "camera", "point_id", "u", "v"]
    for k, pose in enumerate(poses):
        markers = pd.read_csv(tmp_path / "results" / "markers" / f"i{k}.csv", dtype={"point_id": str},
                              keep_default_na=False)
        assert list(markers.columns) == ["u", "v", "score", "sigma_px", "fit_residual", "point_id"]
        assert markers["sigma_px"].between(0, 0.5).all()
        ours = observations[observations["image"] == f"i{k}"]
        assert len(ours) >= 8
        truth = SMALL.project(pose.apply(control.loc[ours["point_id"], ["x", "y", "z"]].to_numpy()))
        np.testing.assert_array_less(np.hypot(*(truth - ours[["u", "v"]].to_numpy()).T), 0.3)
    hand = observations[observations["image"] == "hand"]
    assert hand[["point_id", "u", "v"]].values.tolist() == [["L03", 100.5, 200.25]]
    assert (hand["camera"] == "C0").all()
    Dataset.load(tmp_path / "data")  # untouched


def test_per_image_jobs_and_stage_collection_equal_one_run(tmp_path):
    small_dataset(tmp_path / "data")
    whole = Workspace.open(tmp_path / "data", tmp_path / "whole")
    markers_stage.run(whole)
    jobs = Workspace.open(tmp_path / "data", tmp_path / "jobs")
    for image in ("i1", "i0"):
        assert markers_stage.run_image(jobs, image) == [tmp_path / "jobs" / "markers" / f"{image}.csv"]
    with pytest.raises(DmaisError, match="'hand'"):  # observations given: nothing to extract
        markers_stage.run_image(jobs, "hand")
    [collected] = markers_stage.collect(jobs, "intrinsics")
    assert collected == tmp_path / "jobs" / "observations" / "intrinsics.csv"
    per_stage = Workspace.open(tmp_path / "data", tmp_path / "jobs").load_observations()
    pd.testing.assert_frame_equal(per_stage.sort_values(["image", "point_id"]).reset_index(drop=True),
                                  whole.load_observations().sort_values(["image", "point_id"]).reset_index(drop=True))
    (tmp_path / "jobs" / "markers" / "i0.csv").unlink()
    with pytest.raises(DmaisError, match="i0.csv"):
        markers_stage.collect(jobs, "intrinsics")


def test_markers_stage_missing_or_corrupt_image(tmp_path):
    small_dataset(tmp_path / "data")
    workspace = Workspace.open(tmp_path / "data", tmp_path / "results")
    (tmp_path / "data" / "images" / "i1.png").unlink()
    with pytest.raises(DatasetError, match="i1"):
        markers_stage.run(workspace)
    assert not (tmp_path / "results").exists()  # checked before any work
    (tmp_path / "data" / "images" / "i1.png").write_bytes(b"not a png")
    with pytest.raises(DatasetError, match="i1.*cannot be decoded"):
        markers_stage.run(workspace)


def test_markers_say_why_nothing_is_identified(tmp_path, caplog):
    """Without an attitude prior, or without focal_px, detections cannot be identified: the image's
    job says which input is missing instead of silently reporting 0 identified."""
    small_dataset(tmp_path / "data")
    images = pd.read_csv(tmp_path / "data" / "images.csv", dtype=str, keep_default_na=False)
    images.loc[images["image"] == "i0", ["prior_qw", "prior_qx", "prior_qy", "prior_qz"]] = ""
    images.to_csv(tmp_path / "data" / "images.csv", index=False)
    with caplog.at_level("WARNING", logger="dmais_pipe.markers.extract"):
        markers_stage.run_image(Workspace.open(tmp_path / "data", tmp_path / "results"), "i0")
        markers_stage.run_image(Workspace.open(tmp_path / "data", tmp_path / "results"), "i1")
    said = [r.getMessage() for r in caplog.records]
    assert len(said) == 1 and said[0].startswith("markers i0: ") and "none can be identified" in said[0], said
    assert said[0].endswith("intrinsics images are identified from their prior centre and attitude and the camera's "
                            "focal_px; missing prior_qw..prior_qz (attitude) in images.csv"), said

    manifest = (tmp_path / "data" / "dataset.yaml").read_text().replace("focal_px: 2000.0", "")
    (tmp_path / "data" / "dataset.yaml").write_text(manifest)
    caplog.clear()
    with caplog.at_level("WARNING", logger="dmais_pipe.markers.extract"):
        markers_stage.run_image(Workspace.open(tmp_path / "data", tmp_path / "results"), "i1")
    assert [r.getMessage().split("; ")[-1] for r in caplog.records] == ["missing focal_px of camera C0 in dataset.yaml"]
    workspace = Workspace.open(tmp_path / "data", tmp_path / "results")
    markers_stage.collect(workspace, "intrinsics")
    with pytest.raises(DmaisError, match=r"camera C0: none of its 2 calibration images has an identified observation"):
        intrinsics.run(workspace)


def test_pose_verification_drops_swapped_ids_and_keeps_the_rest():
    camera = Camera(44300.0, 44350.0, 2060.0, 1490.0, 2.5, 4096, 3000)
    rng = np.random.default_rng(5)
    points = field(rng)
    table = pd.DataFrame(points, columns=["x", "y", "z"], index=[f"P{k:03d}" for k in range(len(points))])
    uv = camera.project(points)
    seen = np.flatnonzero(camera.in_image(uv, margin=20))
    ids = table.index.to_numpy(dtype=object)[seen]
    detections = uv[seen] + rng.normal(0, 0.05, (len(seen), 2))
    verified = verify_with_pose(detections, ids, table, (2047.5, 1499.5))
    np.testing.assert_array_equal(verified, ids)  # distortion of a d = 2.5 camera stays inside the gate
    swapped = ids.copy()
    swapped[[0, 1]] = swapped[[1, 0]]
    verified = verify_with_pose(detections, swapped, table, (2047.5, 1499.5))
    assert not np.any((verified != "") & (verified != ids))  # no wrong id survives
    assert np.count_nonzero(verified == ids) >= len(ids) - 2
    assert np.all(verify_with_pose(detections[:3], ids[:3], table, (2047.5, 1499.5)) == "")  # too few to verify
