"""Coordinate reference systems (issue 41): geo.py's conversions against constructions written out by
hand here, a dataset in UTM 33N and WGS 84 read into the computation frame, poses.csv's lat/lon/h and
NED attitude against the same observations solved in a local ENU frame, and bad inputs."""

from __future__ import annotations

import logging
import shutil
import struct
import numpy as np
import pandas as pd
import pyproj
import pytest
import yaml

from conftest import observation_only
from dmais_pipe import geo
from dmais_pipe.cli import main
from dmais_pipe.dataset import Dataset
from dmais_pipe.files import copy_atomic
from dmais_pipe.geometry import euler_zyx_rates, exp_so3, rotation_error, rotation_from_euler_zyx, rotation_from_quat
from dmais_pipe.stages import intrinsics, pose
from dmais_pipe.workspace import CENTER, QUAT, Workspace

ORIGIN = (35.0, 17.8, 100.0)
ARCMIN = 60.0 * 180.0 / np.pi


def hand_ned_from_ecef(lat_deg, lon_deg) -> np.ndarray:
    """(n, 3, 3) rows north, east, down of the local level frame, from geodetic latitude and
    longitude: the textbook rotation, written out here independently of geo.py."""
    phi, lam = np.radians(np.atleast_1d(lat_deg)), np.radians(np.atleast_1d(lon_deg))
    sp, cp, sl, cl = np.sin(phi), np.cos(phi), np.sin(lam), np.cos(lam)
    zero = np.zeros_like(phi)
    return np.stack([np.stack([-sp * cl, -sp * sl, cp], -1),
                     np.stack([-sl, cl, zero], -1),
                     np.stack([-cp * cl, -cp * sl, -sp], -1)], axis=1)


def hand_ecef_from_enu_rotation(lat_deg, lon_deg) -> np.ndarray:
    """(3, 3) columns east, north, up of the topocentric frame at (lat, lon) in ECEF, by hand."""
    ned = hand_ned_from_ecef(lat_deg, lon_deg)[0]
    return np.column_stack([ned[1], ned[0], -ned[2]])


def geodetic_sim(name: str, crs: str | None, frames_per_group: int = 2) -> dict:
    """A small observation-only copy of config/simulate/geodetic.yaml (crs None: the local twin:
    the same world, observations and noise draws written in the ENU frame at the origin)."""
    settings = yaml.safe_load(open("config/simulate/geodetic.yaml"))
    small = observation_only(name, settings["seed"], calib_images=6, eval_images=1, frames_per_group=frames_per_group)
    small["flight"] = {**settings["flight"], **small["flight"]}
    small["geodetic"] = {**settings["geodetic"], "crs": crs}
    return small


# ------------------------------------------------------------------------------ conversions


def test_ned_from_ecef_is_the_rotation_written_by_hand():
    rng = np.random.default_rng(1)
    geodetic = np.column_stack([rng.uniform(-89.5, 89.5, 50), rng.uniform(-180, 180, 50), rng.uniform(-100, 9000, 50)])
    ours = geo.ned_from_ecef(geodetic)
    assert np.abs(ours - hand_ned_from_ecef(geodetic[:, 0], geodetic[:, 1])).max() < 1e-9
    assert np.abs(ours @ np.swapaxes(ours, 1, 2) - np.eye(3)).max() < 1e-12


def test_the_computation_frame_is_ecef_turned_and_moved():
    rotation = geo.ecef_from_enu_rotation(ORIGIN)
    assert np.abs(rotation - hand_ecef_from_enu_rotation(*ORIGIN[:2])).max() < 1e-9
    assert np.abs(geo.enu_from_ecef(ORIGIN, geo.ecef_from_geodetic(ORIGIN))).max() < 1e-6  # the origin is 0
    rng = np.random.default_rng(2)
    enu = rng.uniform(-20000, 20000, (20, 3))
    ecef = geo.ecef_from_enu(ORIGIN, enu)
    # distances are the Earth's, and the frame's axes the hand-made rotation's
    assert np.allclose(np.linalg.norm(enu[1:] - enu[0], axis=1), np.linalg.norm(ecef[1:] - ecef[0], axis=1),
                       rtol=0, atol=1e-6)
    assert np.abs((ecef[1:] - ecef[0]) - (enu[1:] - enu[0]) @ rotation.T).max() < 1e-6


def test_utm_zone_edge_is_not_metric_but_the_computation_frame_is():
    """At longitude 17.96 deg, UTM 33N's grid distances are 1.0005 x the true ones on the ellipsoid:
    the reason the pipeline never computes in a map projection."""
    frame = geo.Geo("EPSG:32633", "EPSG:4979", ORIGIN)
    a, b = np.array([[770000.0, 3877000.0, 0.0]]), np.array([[770100.0, 3877000.0, 0.0]])
    enu = frame.enu_from_crs(np.vstack([a, b]))
    true = np.linalg.norm(enu[1] - enu[0])
    lat, lon, _ = frame.geodetic_from_enu((enu[0] + enu[1]) / 2)[0]
    factors = pyproj.Proj("EPSG:32633").get_factors(lon, lat)
    assert 100.0 / true == pytest.approx(factors.meridional_scale, rel=1e-7)
    assert 1.00045 < 100.0 / true < 1.00055
    assert np.abs(frame.crs_from_enu(enu) - np.vstack([a, b])).max() < 1e-6  # round trip


def test_ned_sigmas_turn_the_covariance_and_keep_a_rescaled_diagonal():
    rng = np.random.default_rng(3)
    A = rng.normal(size=(4, 6, 6))
    covariance = A @ np.swapaxes(A, 1, 2) * 1e-6
    turn = exp_so3(rng.normal(size=(4, 3)) * 0.01)  # ned_from_world near identity
    world = np.array([[30.0, 2.0, -1.0]] * 4)
    ned = world + [[0.5, 0.1, 0.2]]
    E = euler_zyx_rates(np.radians(world))
    angles = np.linalg.inv(E) @ covariance[:, :3, :3] @ np.swapaxes(np.linalg.inv(E), 1, 2)
    sigma_position = np.sqrt(np.diagonal(covariance[:, 3:, 3:], axis1=1, axis2=2))
    sigma_attitude = np.sqrt(np.diagonal(angles, axis1=1, axis2=2)) * ARCMIN
    position, attitude = geo.ned_sigmas(turn, world, ned, sigma_position, sigma_attitude, covariance)
    expected = np.sqrt(np.diagonal(turn @ covariance[:, 3:, 3:] @ np.swapaxes(turn, 1, 2), axis1=1, axis2=2))
    assert np.allclose(position, expected, rtol=1e-12)
    E_ned = euler_zyx_rates(np.radians(ned))
    direct = np.linalg.inv(E_ned) @ covariance[:, :3, :3] @ np.swapaxes(np.linalg.inv(E_ned), 1, 2)
    assert np.allclose(attitude, np.sqrt(np.diagonal(direct, axis1=1, axis2=2)) * ARCMIN, rtol=1e-9)
    doubled, _ = geo.ned_sigmas(np.broadcast_to(np.eye(3), (4, 3, 3)), world, ned, 2 * sigma_position,
                                sigma_attitude, covariance)
    assert np.allclose(doubled, 2 * sigma_position, rtol=1e-12)  # re-solved sigmas: the diagonal follows them


# ------------------------------------------------------------------------------ a dataset in UTM and WGS 84


def test_dataset_in_utm_and_wgs84_loads_into_the_enu_frame(simulated_dataset):
    root = simulated_dataset(geodetic_sim("geo-crs", "EPSG:32633"))
    dataset = Dataset.load(root)
    assert dataset.geo == geo.Geo("EPSG:32633", "EPSG:4979", ORIGIN)
    # the surveyed UTM coordinates, converted by pyproj alone and turned by the hand-made rotation
    surveyed = pd.read_csv(root / "control_points.csv", dtype={"point_id": str}).set_index("point_id")
    to_ecef = pyproj.Transformer.from_crs("EPSG:32633", "EPSG:4978", always_xy=True)
    ecef = np.column_stack(to_ecef.transform(*surveyed[["x", "y", "z"]].to_numpy(float).T))
    origin = np.column_stack(pyproj.Transformer.from_crs("EPSG:4979", "EPSG:4978", always_xy=True).transform(
        ORIGIN[1], ORIGIN[0], ORIGIN[2]))
    expected = (ecef - origin) @ hand_ecef_from_enu_rotation(*ORIGIN[:2])
    assert np.abs(dataset.control_points.loc[surveyed.index, ["x", "y", "z"]].to_numpy(float) - expected).max() < 1e-6
    # and they are the truth (the simulator's frame) plus the 1 mm survey noise
    truth = pd.read_csv(root / "truth" / "control_points.csv", dtype={"point_id": str}).set_index("point_id")
    assert np.abs(expected - truth.loc[surveyed.index, ["x", "y", "z"]].to_numpy(float)).max() < 0.006
    frames = pd.read_csv(root / "truth" / "frames.csv", dtype={"frame": str}).set_index("frame")
    pos = dataset.frames.set_index("frame")[["pos_x", "pos_y", "pos_z"]]
    assert np.linalg.norm(pos.to_numpy(float) - frames.loc[pos.index, ["x", "y", "z"]].to_numpy(float), axis=1).max() < 0.5


@pytest.fixture(scope="module")
def solved(simulated_dataset, tmp_path_factory):
    """The same observations in UTM 33N + WGS 84 (with the simulator's origin and with the default
    one) and in the local ENU frame, each solved by the pose stage with the simulator's rig;
    {run: (workspace, poses.csv as written)}."""
    crs = simulated_dataset(geodetic_sim("geo-crs", "EPSG:32633"))
    local = simulated_dataset(geodetic_sim("geo-local", None))
    default = tmp_path_factory.mktemp("geo-default") / "dataset"
    shutil.copytree(crs, default)
    manifest = yaml.safe_load((default / "dataset.yaml").read_text())
    del manifest["origin"]
    (default / "dataset.yaml").write_text(yaml.safe_dump(manifest))
    runs = {}
    for run, root in (("crs", crs), ("local", local), ("default", default)):
        workspace = Workspace.open(root, tmp_path_factory.mktemp(f"geo-{run}-results"))
        copy_atomic(root / "truth" / "rig.json", workspace.rig_path)
        pose.run(workspace)
        runs[run] = workspace, pd.read_csv(workspace.poses_path(), dtype={"frame": str, "group": str})
    return runs


def test_poses_in_crs_equal_the_local_runs(solved):
    (_, crs), (local_ws, local) = solved["crs"], solved["local"]
    assert list(crs["frame"]) == list(local["frame"])
    # x, y, z in UTM are pyproj's conversion of lat/lon/h (1 mm), and that point is the local run's centre
    to_utm = pyproj.Transformer.from_crs("EPSG:4979", "EPSG:32633", always_xy=True)
    utm = np.column_stack(to_utm.transform(crs["lon_deg"], crs["lat_deg"], crs["h_m"]))
    assert np.abs(utm - crs[list(CENTER)].to_numpy(float)).max() < 1e-3
    local_geodetic = geo.geodetic_from_ecef(geo.ecef_from_enu(ORIGIN, local[list(CENTER)].to_numpy(float)))
    ecef = [geo.ecef_from_geodetic(g) for g in (crs[["lat_deg", "lon_deg", "h_m"]].to_numpy(float), local_geodetic)]
    assert np.linalg.norm(ecef[0] - ecef[1], axis=1).max() < 1e-3
    assert local_ws.dataset.geo is None and "lat_deg" not in local.columns  # no crs: no new columns


def test_ned_attitude_against_a_construction_by_hand(solved):
    """ned_from_rig from the local run's rig_from_world and the NED rotation written out here from
    the frame's latitude and longitude: the crs run's ned_* angles within 0.01'."""
    (_, crs), (_, local) = solved["crs"], solved["local"]
    enu_from_rig = np.swapaxes(rotation_from_quat(local[list(QUAT)].to_numpy(float)), 1, 2)
    ned_from_enu = hand_ned_from_ecef(crs["lat_deg"], crs["lon_deg"]) @ hand_ecef_from_enu_rotation(*ORIGIN[:2])
    expected = ned_from_enu @ enu_from_rig
    written = rotation_from_euler_zyx(np.radians(crs[["ned_heading_deg", "ned_pitch_deg", "ned_roll_deg"]].to_numpy(float)))
    assert rotation_error(written, expected).max() * ARCMIN < 0.01
    assert ((crs["ned_heading_deg"] >= 0) & (crs["ned_heading_deg"] < 360)).all()
    assert crs["ned_roll_deg"].abs().max() < 5  # a nadir rig is level in NED (roll ~180 in ENU)


def test_errors_against_truth_match_the_local_run_with_either_origin(solved):
    local_ws, local = solved["local"]
    truth = pd.read_csv(solved["crs"][0].dataset.truth_dir / "frames.csv", dtype={"frame": str}).set_index("frame")
    truth = truth.loc[local["frame"]]
    true_ecef = geo.ecef_from_geodetic(truth[["lat_deg", "lon_deg", "h_m"]].to_numpy(float))
    true_ned = rotation_from_euler_zyx(np.radians(truth[["ned_heading_deg", "ned_pitch_deg", "ned_roll_deg"]].to_numpy(float)))
    local_position = np.linalg.norm(geo.ecef_from_enu(ORIGIN, local[list(CENTER)].to_numpy(float)) - true_ecef, axis=1)
    local_attitude = rotation_error(rotation_from_quat(local[list(QUAT)].to_numpy(float)),
                                    rotation_from_quat(truth[list(QUAT)].to_numpy(float))) * ARCMIN
    for run in ("crs", "default"):
        poses = solved[run][1]
        position = np.linalg.norm(geo.ecef_from_geodetic(poses[["lat_deg", "lon_deg", "h_m"]].to_numpy(float))
                                  - true_ecef, axis=1)
        ned = rotation_from_euler_zyx(np.radians(poses[["ned_heading_deg", "ned_pitch_deg", "ned_roll_deg"]].to_numpy(float)))
        attitude = rotation_error(ned, true_ned) * ARCMIN
        rms = lambda v: float(np.sqrt(np.mean(v ** 2)))  # noqa: E731
        assert rms(position) <= 1.05 * rms(local_position) + 0.002, run
        assert rms(attitude) <= 1.05 * rms(local_attitude) + 0.02, run


def test_ned_sigmas_are_the_world_ones_turned(solved):
    """Near the origin NED is ENU with north and east swapped and up reversed, so the sigmas agree
    to the frames' small turn; at 15 km the turn is 0.13 deg."""
    poses = solved["crs"][1]
    assert np.isfinite(poses[["sigma_north_m", "sigma_ned_heading_arcmin"]].to_numpy(float)).all()
    assert np.allclose(poses["sigma_north_m"], poses["sigma_y_m"], rtol=0.02)
    assert np.allclose(poses["sigma_east_m"], poses["sigma_x_m"], rtol=0.02)
    assert np.allclose(poses["sigma_down_m"], poses["sigma_z_m"], rtol=0.02)
    assert np.allclose(poses["sigma_ned_heading_arcmin"], poses["sigma_heading_arcmin"], rtol=0.05)


def test_focal_lengths_equal_the_local_runs(simulated_dataset, tmp_path):
    focal = {}
    for name, crs in (("geo-crs", "EPSG:32633"), ("geo-local", None)):
        root = simulated_dataset(geodetic_sim(name, crs))
        workspace = Workspace.open(root, tmp_path / str(crs))
        intrinsics.run_cameras(workspace, ["C0"], intrinsics.CONFS["ours"])
        focal[crs] = workspace.load_intrinsics("C0")[0]
    assert focal["EPSG:32633"].fx == pytest.approx(focal[None].fx, abs=1e-3)
    assert focal["EPSG:32633"].fy == pytest.approx(focal[None].fy, abs=1e-3)


def _wkb_points(wkb: bytes) -> np.ndarray:
    """(k, 3) coordinates of a little-endian ISO WKB Point Z or Polygon Z (one ring), decoded here."""
    kind = struct.unpack_from("<I", wkb, 1)[0] & 0xFF
    if kind == 1:
        return np.array(struct.unpack_from("<3d", wkb, 5))[None]
    count = struct.unpack_from("<I", wkb, 9)[0]
    return np.array(struct.unpack_from(f"<{3 * count}d", wkb, 13)).reshape(count, 3)


def test_geojson_export_reads_back_in_gdal(solved):
    """dmais export-geojson read back by GDAL (pyogrio): every frame's point at its poses.csv
    lat/lon/h with its attributes, and C0's footprints the size a 350 m flight gives (area by
    pyproj's geodesic polygon area) around the frame's nadir."""
    pyogrio = pytest.importorskip("pyogrio")
    from pyogrio import raw

    workspace, poses = solved["crs"]
    assert main(["export-geojson", str(workspace.dataset.root), "--out", str(workspace.root)]) == 0
    frames, footprints = (workspace.root / "geojson" / f"{name}.geojson" for name in ("frames", "footprints"))
    info = pyogrio.read_info(frames)
    assert info["geometry_type"] == "Point Z" and info["features"] == len(poses)
    assert pyproj.CRS(info["crs"]).equals(pyproj.CRS("EPSG:4979"))
    meta, _, geometry, fields = raw.read(frames)
    values = dict(zip(meta["fields"], fields))
    assert list(values["frame"]) == list(poses["frame"])
    lon_lat_h = np.vstack([_wkb_points(g) for g in geometry])
    assert np.allclose(lon_lat_h, poses[["lon_deg", "lat_deg", "h_m"]].to_numpy(), rtol=0, atol=1e-9)
    assert np.allclose(values["sigma_ned_roll_arcmin"], poses["sigma_ned_roll_arcmin"]) and set(values["camera_set"]) == {"01234"}
    meta, _, geometry, fields = raw.read(footprints)
    values = dict(zip(meta["fields"], fields))
    assert meta["geometry_type"] == "Polygon Z" and len(geometry) == 5 * len(poses)
    geod = pyproj.Geod(ellps="WGS84")
    ground = workspace.dataset.geo.geodetic_from_enu(workspace.dataset.ground_points[["x", "y", "z"]].to_numpy(float))
    rig = workspace.load_rig()
    for k in np.flatnonzero(values["camera"] == "C0"):
        ring = _wkb_points(geometry[k])
        assert np.allclose(ring[0], ring[-1])  # closed
        area, _ = geod.polygon_area_perimeter(ring[:-1, 0], ring[:-1, 1])
        assert area > 0  # counter-clockwise, as RFC 7946 asks
        frame = poses.set_index("frame").loc[values["frame"][k]]
        above = frame["h_m"] - np.median(ground[:, 2][np.abs(ground[:, 0] - frame["lat_deg"]) < 0.01])
        camera = rig.cameras["C0"]
        expected = above ** 2 * (camera.width - 1) * (camera.height - 1) / (camera.fx * camera.fy)
        assert area == pytest.approx(expected, rel=0.1)
        centre = ring[:-1, :2].mean(axis=0)
        _, _, distance = geod.inv(centre[0], centre[1], frame["lon_deg"], frame["lat_deg"])
        assert distance < 0.05 * above  # C0 looks down


# ------------------------------------------------------------------------------ bad inputs


@pytest.fixture
def utm_dataset(simulated_dataset, tmp_path):
    """A copy of the small UTM dataset to spoil."""
    copy = tmp_path / "dataset"
    shutil.copytree(simulated_dataset(geodetic_sim("geo-crs", "EPSG:32633")), copy)
    return copy


def _set_manifest(root, **changes):
    manifest = yaml.safe_load((root / "dataset.yaml").read_text())
    for key, value in changes.items():
        if value is None:
            manifest.pop(key, None)
        else:
            manifest[key] = value
    (root / "dataset.yaml").write_text(yaml.safe_dump(manifest))


@pytest.mark.parametrize("changes, message", [
    ({"crs": "EPSG:99999"}, "dataset.yaml: crs: 'EPSG:99999' is not a coordinate reference system pyproj knows"),
    ({"pos_crs": "WGS 99"}, "dataset.yaml: pos_crs: 'WGS 99' is not a coordinate reference system"),
    ({"crs": None}, "dataset.yaml: pos_crs is given without crs"),
    ({"crs": "EPSG:2056"}, "control_points.csv, line 2: x, y, z (755"),  # Swiss grid: ~27 deg north of Switzerland
    ({"crs": "EPSG:32633+5773"}, "needs the grid us_nga_egm96_15.tif"),
    ({"origin": {"lat_deg": 95, "lon_deg": 0, "h_m": 0}}, "origin.lat_deg must be a number within +-90"),
])
def test_bad_crs_is_one_line_exit_2_and_nothing_written(utm_dataset, tmp_path, capsys, changes, message):
    _set_manifest(utm_dataset, **changes)
    assert message in refused_in_one_line(utm_dataset, tmp_path / "results", capsys)


def refused_in_one_line(dataset, out, capsys) -> str:
    """`dmais pose DATASET --out OUT`'s one error line, after checking its exit status 2, that it
    wrote nothing and left the dataset's files as they were."""
    before = {p: p.stat().st_mtime_ns for p in dataset.rglob("*")}
    assert main(["pose", str(dataset), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert not out.exists() or not any(out.iterdir())
    assert {p: p.stat().st_mtime_ns for p in dataset.rglob("*")} == before
    return lines[0]


def test_far_outside_names_the_area_and_near_outside_warns(utm_dataset, caplog):
    _set_manifest(utm_dataset, crs="EPSG:2056")
    with pytest.raises(Exception, match=r"deg outside the area of use of crs 'EPSG:2056'"):
        Dataset.load(utm_dataset)
    _set_manifest(utm_dataset, crs="EPSG:32633")
    points = pd.read_csv(utm_dataset / "control_points.csv", dtype=str)
    points.loc[3, "x"] = "800000.0"  # 18.3 deg E: east of zone 33, 0.3 deg
    points.to_csv(utm_dataset / "control_points.csv", index=False)
    with caplog.at_level(logging.WARNING, logger="dmais_pipe.dataset"):
        Dataset.load(utm_dataset)
    warned = [r.getMessage() for r in caplog.records if "outside the area of use" in r.getMessage()]
    assert len(warned) == 1 and "1 row(s)" in warned[0] and "line 5" in warned[0], warned


def test_geojson_export_without_crs_is_refused_in_one_line(solved, capsys):
    workspace, _ = solved["local"]
    assert main(["export-geojson", str(workspace.dataset.root), "--out", str(workspace.root)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "names no crs" in err[0]
    assert not (workspace.root / "geojson").exists()
