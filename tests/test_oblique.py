"""The oblique aerial preset (config/simulate/oblique.yaml, issue 30): OpenCV-model cameras in the
simulator and renderer, the preset at a reduced scale through intrinsics -> extrinsics -> pose, and
the report's accuracy table beside other runs."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pandas as pd
import pytest
import yaml
from scipy import ndimage

from dmais_pipe.camera import Camera
from dmais_pipe.dataset import Dataset
from dmais_pipe.errors import ConfigError
from dmais_pipe.geometry import Rigid3, log_so3
from dmais_pipe.report.html import accuracy_table, comparison_runs, run_description
from dmais_pipe.rig import Rig
from dmais_pipe.sim.config import DEFAULTS, load_config, merge
from dmais_pipe.sim.render import board_pixel_bbox, coverage_image, render_image
from dmais_pipe.sim.scene import build_rig, rig_camera
from dmais_pipe.stages import evaluate, extrinsics, intrinsics, markers, pose, report
from dmais_pipe.workspace import Workspace
from test_render import FLAT, POSE, QUIET, board_at, projected_corners, refine, start_offsets

ROOT = Path(__file__).resolve().parents[1]
PRESET = ROOT / "config" / "simulate" / "oblique.yaml"


def reduced_preset() -> dict:
    """The preset at a reduced scale: 6 + 2 calibration images per camera, one site of two groups
    of 3 frames (the rig, lens, field and noise budget unchanged)."""
    settings = yaml.safe_load(PRESET.read_text())
    settings["name"] = "oblique-small"
    settings["intrinsics"].update(calib_images_per_camera=6, eval_images_per_camera=2)
    settings["flight"].update(frames_per_group=3, sites={"A": {"center_m": [1500.0, -800.0, 45.0], "groups": [1, 2]}})
    return settings


@pytest.fixture(scope="module")
def small(simulated_dataset):
    return simulated_dataset(reduced_preset())


# ------------------------------------------------------------------------------ the preset


def test_the_preset_is_a_five_camera_oblique_system_with_an_opencv_lens():
    config = load_config(PRESET)
    rig = build_rig(config["rig"])
    axes = {name: rig.cam_from_rig[name].R[2] for name in rig.camera_names}  # optical axes in the rig frame
    assert np.allclose(axes["C0"], [0.0, 0.0, 1.0])
    # C1 back (+y), C2 left (-x), C3 forward (-y), C4 right (+x), each 45 deg from the nadir camera.
    for name, direction in (("C1", [0, 1]), ("C2", [-1, 0]), ("C3", [0, -1]), ("C4", [1, 0])):
        assert abs(np.degrees(np.arccos(axes[name][2])) - 45.0) < 0.5, name
        assert np.degrees(np.arccos(axes[name][:2] @ direction / np.linalg.norm(axes[name][:2]))) < 1.0, name
    for name, camera in rig.cameras.items():
        assert (camera.model, camera.width, camera.height) == ("opencv", 14000, 10000)
        assert abs(camera.fx - 12000.0) < 20.0 and abs(camera.fy - 12000.0) < 20.0
        assert 1.0 < np.hypot(camera.cx - 6999.5, camera.cy - 4999.5) < 10.0  # a few px off the centre
        assert not camera.folds_in_image
        corners = np.array([[0.0, 0.0], [13999.0, 9999.0]])
        radial = np.linalg.norm(camera.undistort(corners) - corners, axis=1)
        tangential = np.linalg.norm(Camera(camera.fx, camera.fy, camera.cx, camera.cy, camera.d, 14000, 10000,
                                           "opencv", k2=camera.k2, k3=camera.k3).undistort(corners)
                                    - camera.undistort(corners), axis=1)
        assert np.all((50.0 < radial) & (radial < 150.0)), name  # about 100 px at the corners
        assert np.all((0.3 < tangential) & (tangential < 5.0)), name  # about 1 px


def test_a_rig_camera_entry_is_checked_against_its_model():
    entry = {"model": "opencv", "fx": 1000.0, "fy": 1000.0, "cx": 99.5, "cy": 79.5, "k1": 0.01, "p2": 1e-4,
             "euler_zyx_deg": [0, 0, 0], "center_m": [0, 0, 0]}
    camera = rig_camera("C9", entry, 200, 160)
    assert camera.distortion == (0.01, 0.0, 0.0, 1e-4, 0.0)
    for change, message in (({"model": "fisheye"}, "'rig.cameras.C9.model' is 'fisheye'"),
                            ({"d": 0.1}, "unknown key.*d for model opencv"),
                            ({"model": "radial1"}, "unknown key.*k1, p2 for model radial1"),
                            ({"fx": None}, "missing fx")):
        bad = {k: v for k, v in {**entry, **change}.items() if v is not None}
        with pytest.raises(ConfigError, match=message):
            rig_camera("C9", bad, 200, 160)
    radial1 = {k: v for k, v in entry.items() if k not in ("model", "k1", "p2")}
    with pytest.raises(ConfigError, match="missing d"):
        rig_camera("C9", radial1, 200, 160)
    assert rig_camera("C9", {**radial1, "d": 0.5}, 200, 160) == Camera(1000.0, 1000.0, 99.5, 79.5, 0.5, 200, 160)
    # The paper's rig (no model key) is built as before.
    assert all(c.model == "radial1" for c in build_rig(merge(DEFAULTS, {})["rig"]).cameras.values())


def test_a_preset_with_a_faulty_camera_entry_is_refused_naming_the_file(tmp_path):
    preset = yaml.safe_load(PRESET.read_text())
    preset["rig"]["cameras"]["C2"]["d"] = 0.03
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(preset))
    with pytest.raises(ConfigError, match=r"bad.yaml: simulator setting 'rig.cameras.C2': unknown key\(s\) d for "
                                          r"model opencv \(its coefficients: k1, k2, p1, p2, k3\)"):
        load_config(tmp_path / "bad.yaml")


def test_the_dataset_names_each_cameras_model(small):
    dataset = Dataset.load(small)
    assert {spec.model for spec in dataset.cameras.values()} == {"opencv"}
    truth = Rig.load(small / "truth" / "rig.json")
    preset = load_config(PRESET)["rig"]["cameras"]
    for name, camera in truth.cameras.items():
        assert camera.distortion == tuple(preset[name][k] for k in ("k1", "k2", "p1", "p2", "k3"))
    assert yaml.safe_load((small / "dataset.yaml").read_text())["cameras"]["C3"]["model"] == "opencv"


def _cv2_projections(root: Path, observations: pd.DataFrame, distortion: bool = True) -> np.ndarray:
    """cv2.projectPoints of each observation's true point with its image's true pose and the truth
    rig's K and distortion vector (n, 2)."""
    truth = Rig.load(root / "truth" / "rig.json")
    points = pd.concat([pd.read_csv(root / "truth" / f"{name}.csv", dtype={"point_id": str})
                        for name in ("control_points", "ground_points")]).set_index("point_id")
    images = pd.read_csv(root / "truth" / "images.csv", dtype={"image": str}).set_index("image")
    out = np.full((len(observations), 2), np.nan)
    for image, rows in observations.groupby("image"):
        shot = images.loc[image]
        pose = Rigid3.from_quat(shot[["qw", "qx", "qy", "qz"]].to_numpy(float),
                                shot[["tx", "ty", "tz"]].to_numpy(float))
        camera = truth.cameras[shot["camera"]]
        dist = np.array(camera.distortion) if distortion else np.zeros(5)
        uv, _ = cv2.projectPoints(points.loc[rows["point_id"], ["x", "y", "z"]].to_numpy(float),
                                  cv2.Rodrigues(pose.R)[0], pose.t, camera.K, dist)
        out[observations.index.get_indexer(rows.index)] = uv.reshape(-1, 2)
    return out


def test_simulated_pixels_are_opencvs_projection_of_the_truth_plus_the_stated_noise(small):
    """truth/observations.csv is cv2.projectPoints of the true points (1e-6 px); observations.csv
    adds the preset's noise: 0.1 px per axis on the calibration images, 0.5 px in flight."""
    truth = pd.read_csv(small / "truth" / "observations.csv", dtype={"image": str, "point_id": str})
    expected = _cv2_projections(small, truth)
    np.testing.assert_allclose(truth[["u", "v"]].to_numpy(float), expected, atol=1e-6)
    # The lens matters: without its distortion the same points land up to ~100 px away.
    undistorted = _cv2_projections(small, truth, distortion=False)
    assert np.max(np.linalg.norm(undistorted - expected, axis=1)) > 50.0
    measured = pd.read_csv(small / "observations.csv", dtype={"image": str, "point_id": str})
    stage = pd.read_csv(small / "images.csv", dtype={"image": str}).set_index("image")["stage"]
    error = measured[["u", "v"]].to_numpy(float) - _cv2_projections(small, measured)
    for stages, sigma in ((("intrinsics", "extrinsics"), 0.1), (("flight",), 0.5)):
        rows = measured["image"].map(stage).isin(stages).to_numpy()
        assert rows.sum() > 400
        assert abs(error[rows].std() / sigma - 1.0) < 0.1 and abs(error[rows].mean()) < 0.1 * sigma, stages
        assert np.abs(error[rows]).max() < 6.0 * sigma, stages


@pytest.fixture(scope="module")
def chain(small, tmp_path_factory):
    """The stages on the reduced preset: collect the given observations, intrinsics (ours, model
    opencv from dataset.yaml), extrinsics (pycolmap rig BA with OPENCV cameras), the whole rig's and
    C0's poses, evaluate."""
    workspace = Workspace.open(small, tmp_path_factory.mktemp("oblique-results"))
    for stage in ("intrinsics", "extrinsics", "flight"):
        markers.collect(workspace, stage)
    intrinsics.run(workspace, intrinsics.Conf(methods=("ours",)))
    extrinsics.run(workspace)
    pose.run(workspace)
    pose.run(workspace, cameras=["C0"])
    evaluate.run(workspace)
    return workspace


def test_the_chain_recovers_the_intrinsics(chain, small):
    """Every camera's opencv model from 6 images: focal lengths within 2 px, principal point within
    2 px, and the distortion (about 100 px at the corners) within 3 px everywhere in the image (same
    K, both distortions), the whole camera within 4 px; eps_calib at the noise's level (0.1 px of
    marker noise and 1 mm of survey noise at 40-110 m: ~0.3 px). Measured: <= 0.5, 1.1, 1.4, 2.0 px."""
    truth = Rig.load(small / "truth" / "rig.json")
    u, v = np.meshgrid(np.linspace(0, 13999, 29), np.linspace(0, 9999, 21))
    grid = np.column_stack([u.ravel(), v.ravel()])
    for name, camera in truth.cameras.items():
        record = json.loads(chain.intrinsics_path(name).read_text())
        found = Camera.from_dict(record)
        assert found.model == "opencv"
        assert abs(found.fx - camera.fx) < 2.0 and abs(found.fy - camera.fy) < 2.0, name
        assert np.hypot(found.cx - camera.cx, found.cy - camera.cy) < 2.0, name
        rays = camera.unproject(grid)
        same_k = found.with_parameters(np.r_[camera.parameters[:4], found.parameters[4:]])
        assert np.max(np.linalg.norm(same_k.project(rays) - grid, axis=1)) < 3.0, name
        assert np.max(np.linalg.norm(found.project(rays) - grid, axis=1)) < 4.0, name
        assert 0.2 < record["eps_calib_px"] < 0.4, name


def test_the_chain_recovers_the_rig_and_the_poses(chain, small):
    """Rig rotations within 0.02 deg and centres within 1 cm of the truth (measured <= 0.005 deg,
    2 mm); the whole rig's poses within 0.25 m and 1.2 arc-min on average (the in-flight mounting
    change of 0.15' + 0.3' at 600-1500 m: measured 0.10 m, 0.44'); C0 alone (60 x 45 deg) solves
    every frame too."""
    truth, found = Rig.load(small / "truth" / "rig.json"), chain.load_rig()
    for name in truth.camera_names:
        turn = found.cam_from_rig[name].R @ truth.cam_from_rig[name].R.T
        assert np.degrees(np.linalg.norm(log_so3(turn))) < 0.02, name
        assert np.linalg.norm(found.camera_center(name) - truth.camera_center(name)) < 0.01, name
    assert json.loads(chain.rig_config_path.read_text())[0]["cameras"][0]["camera_model_name"] in ("OPENCV",
                                                                                                  "FULL_OPENCV")
    conf = chain.load_table("conf", ("group", "subset"))
    rows = conf[conf["group"] == "all"].set_index("subset")
    assert rows.loc["01234", "n_frames"] == rows.loc["0", "n_frames"] == 6
    assert rows.loc["01234", "true_pos_err_mean_m"] < 0.25 and rows.loc["01234", "true_ang_err_mean_arcmin"] < 1.2


# ------------------------------------------------------------------------------ rendering


#: The preset's C0 lens at a tenth of the size (same field of view and normalized distortion).
SMALL_OBLIQUE = Camera(1200.43, 1200.18, 700.31, 499.67, 0.0283, 1400, 1000, "opencv", k2=-0.0121, p1=4.1e-5,
                       p2=-5.8e-5, k3=0.0043)
#: A wide-angle opencv lens that folds inside the image (k1 > 0 but k2 < 0: the paper's radial
#: test, d < 0, would not see it).
FOLDING = Camera(500.0, 500.0, 320.3, 239.6, 0.1, 640, 480, "opencv", k2=-0.8, p1=1e-3, p2=-2e-3)


@pytest.mark.parametrize("pixel, roll, tilt, axis", [
    ((700.0, 500.0), 0.3, 0.0, 0.0), ((60.0, 55.0), 0.5, 0.9, 0.2), ((1340.0, 940.0), -0.8, 0.7, 2.0),
    ((1350.0, 60.0), 1.2, 1.0, -1.0),
])
def test_an_opencv_lens_renders_its_corners_at_the_projections(pixel, roll, tilt, axis):
    board = board_at(SMALL_OBLIQUE, POSE, pixel, 40.0, roll=roll, tilt=tilt, tilt_axis=axis)
    image = render_image(SMALL_OBLIQUE, POSE, [board], np.random.default_rng(5), QUIET)
    truth = projected_corners(SMALL_OBLIQUE, POSE, board)
    found = refine(image, truth + start_offsets(1))
    np.testing.assert_array_less(np.linalg.norm(found - truth, axis=1), 0.05)


def test_a_folding_opencv_lens_renders_only_where_it_is_one_to_one():
    radius = FOLDING.max_projectable_radius
    assert FOLDING.folds_in_image and 0.6 < radius < 0.8  # k1 = 0.1 > 0: no d < 0 fold to go by
    # A board inside the one-to-one region, near its edge: its corner where the camera projects it.
    board = board_at(FOLDING, POSE, (545.0, 90.0), 12.0, roll=0.4, tilt=0.6, tilt_axis=1.0)
    truth = projected_corners(FOLDING, POSE, board)
    found = refine(render_image(FOLDING, POSE, [board], np.random.default_rng(6), QUIET), truth + start_offsets(1))
    np.testing.assert_array_less(np.linalg.norm(found - truth, axis=1), 0.05)
    # A board filling the view: drawn inside its box, and nowhere the model cannot undistort (pixels
    # on the fold's edge, partly inside, are partly covered).
    wall = board_at(FOLDING, POSE, (320.0, 240.0), 5.0, cols=2, rows=2, cell=20.0)
    x0, y0, x1, y1 = board_pixel_bbox(FOLDING, POSE, wall)
    image = coverage_image(FOLDING, POSE, [wall], FLAT)
    v, u = np.mgrid[0:480, 0:640]
    unseen = np.isnan(FOLDING.undistort_normalized(np.column_stack([u.ravel(), v.ravel()]))[:, 0]).reshape(480, 640)
    beyond = ndimage.binary_erosion(unseen)  # unseen with every neighbour
    assert beyond.sum() > 1000 and (~unseen).sum() > 200_000
    assert np.all(image[beyond] == FLAT.background_mean)
    inner = ~unseen & (np.hypot(u - FOLDING.cx, v - FOLDING.cy) < 250)
    assert np.all(image[inner] != FLAT.background_mean)
    changed = np.nonzero(image != FLAT.background_mean)
    assert changed[0].min() >= y0 and changed[0].max() < y1 and changed[1].min() >= x0 and changed[1].max() < x1


# ------------------------------------------------------------------------------ the report


def _conf(subsets: dict[str, tuple[float, float, float]], groups=("1", "all")) -> pd.DataFrame:
    """A conf.csv with the given (eps_pos, eps_ang, eps_proj) per subset label, for each group."""
    return pd.DataFrame([{"group": g, "subset": s, "cameras": "+".join(f"C{k}" for k in s), "n_frames": 3,
                          "eps_pos_mean_m": p * (2 if g != "all" else 1), "eps_ang_mean_arcmin": a,
                          "eps_proj_mean_px": e} for g in groups for s, (p, a, e) in subsets.items()])


def test_the_accuracy_table_puts_the_runs_side_by_side_per_subset():
    ours = _conf({"0": (0.17, 0.63, 2.2), "01": (0.12, 0.57, 2.0), "01234": (0.11, 0.41, 1.4)})
    demo = _conf({"0": (9.5, 29.8, 387.0), "1234": (0.11, 0.35, 4.5), "01234": (0.09, 0.32, 4.1)}).assign(
        true_pos_err_mean_m=0.08)
    table = accuracy_table({"oblique": ours, "demo": demo})
    assert list(table["subset"]) == ["0", "01", "01234", "1234"]  # ours first, then the demo's others
    metrics = ("eps_pos_mean_m", "eps_ang_mean_arcmin", "eps_proj_mean_px")
    assert list(table.columns) == (["subset"] + [f"{m} [{run}]" for m in metrics for run in ("oblique", "demo")]
                                   + ["true_pos_err_mean_m [demo]"])
    row = table.set_index("subset")
    assert row.loc["0", "eps_pos_mean_m [oblique]"] == 0.17 and row.loc["0", "eps_pos_mean_m [demo]"] == 9.5
    assert row.loc["01234", "eps_proj_mean_px [demo]"] == 4.1
    assert row.loc["01234", "eps_ang_mean_arcmin [oblique]"] == 0.41
    assert np.isnan(row.loc["01", "eps_pos_mean_m [demo]"]) and np.isnan(row.loc["1234", "eps_pos_mean_m [oblique]"])


def test_comparison_runs_are_siblings_by_name_or_paths(tmp_path):
    results = tmp_path / "results" / "oblique"
    elsewhere = tmp_path / "elsewhere"
    runs = comparison_runs(results, ["demo", str(elsewhere / "paper"), "oblique", "demo", str(elsewhere / "oblique")])
    assert runs == {"demo": tmp_path / "results" / "demo", "paper": elsewhere / "paper",
                    str(elsewhere / "oblique"): elsewhere / "oblique"}  # a name taken: labelled by its path
    described = run_description("oblique", build_rig(load_config(PRESET)["rig"]))
    assert described == {"run": "oblique", "cameras": 5, "image_px": "14000x10000", "focal_px": "12002",
                         "model": "opencv", "fov_deg": "60.5 x 45.2"}


def test_the_report_shows_this_runs_accuracy_beside_the_named_runs(chain, tmp_path):
    """compare_with names a sibling run with a (synthetic) conf.csv and one that was never made: the
    first's numbers stand beside this run's, the second is named with how to make it."""
    sibling = chain.root.parent / "demo-like"
    (sibling / "tables").mkdir(parents=True)
    _conf({"0": (9.54, 29.8, 387.3), "01234": (0.0885, 0.3174, 4.124)}).to_csv(sibling / "tables" / "conf.csv",
                                                                                 index=False)
    Rig.load(chain.dataset.root / "truth" / "rig.json").save(sibling / "rig.json")
    html = tmp_path / "report.html"
    report.run(chain, html, report.Conf(compare_with=("demo-like", "never-made")))
    text = html.read_text()
    section = text[text.index('id="accuracy"'): text.index('id="budget"')]
    for expected in ("eps_pos_mean_m [demo-like]", f"eps_pos_mean_m [{chain.root.name}]", "<td>9.54</td>",
                     "<td>0.0885</td>", "<td>387.3</td>", "never-made/tables/conf.csv is missing",
                     "--configfile config/config.yaml", "<td>14000x10000</td>"):
        assert expected in section, expected
    ours = chain.load_table("conf", ("group", "subset")).set_index(["group", "subset"])
    assert f"<td>{ours.loc[('all', '01234'), 'eps_pos_mean_m']:.4g}</td>" in section
    # Without compare_with the section shows this run alone and says how to add others.
    report.run(chain, html)
    text = html.read_text()
    assert "compare_with=demo" in text[text.index('id="accuracy"'): text.index('id="budget"')]
