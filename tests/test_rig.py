"""Tests of the rig as a generalized camera (paper: v_i = t_c, f_i = R_c K^-1 m~, eq. projEq)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dmais_pipe.camera import Camera
from dmais_pipe.errors import DmaisError
from dmais_pipe.geometry import Rigid3, rotation_from_euler_zyx
from dmais_pipe.rig import Rig

# tab:extrinsics_R (known initial position): ZYX Euler angles (z, y, x) in degrees, rig_from_cam
EULER_DEG = {
    "C1": (-179.811, -0.152, 46.233),
    "C2": (-90.048, -1.170, 44.758),
    "C3": (0.150, -0.047, 44.038),
    "C4": (90.140, 1.180, 45.615),
}
# tab:extrinsics_t (known initial position): camera centres in the rig (C0) frame, metres
CENTRES = {
    "C1": (-0.002, 0.102, -0.086),
    "C2": (-0.113, -0.012, -0.100),
    "C3": (0.000, -0.143, -0.097),
    "C4": (0.122, -0.010, -0.100),
}
# tab:intrinsics-like values ("Ours"), principal points moved a few tens of pixels off centre
INTRINSICS = {
    "C0": (45553.0, 45569.7, 2060.0, 1492.0, 3.0715),
    "C1": (44922.5, 44963.4, 2028.0, 1515.0, 2.0227),
    "C2": (44440.4, 44411.0, 2073.0, 1510.0, -2.2361),
    "C3": (43737.5, 43700.0, 2038.0, 1478.0, 2.2207),
    "C4": (44660.0, 44620.9, 2066.0, 1486.0, 0.0),
}
NAMES = ["C0", "C1", "C2", "C3", "C4"]


def rig_from_cam(name: str) -> Rigid3:
    if name == "C0":
        return Rigid3.identity()
    return Rigid3(rotation_from_euler_zyx(np.radians(EULER_DEG[name])), CENTRES[name])


@pytest.fixture(scope="module")
def rig() -> Rig:
    cameras = {
        name: Camera(fx=fx, fy=fy, cx=cx, cy=cy, d=d, width=4096, height=3000)
        for name, (fx, fy, cx, cy, d) in INTRINSICS.items()
    }
    return Rig(cameras, {name: rig_from_cam(name).inverse() for name in NAMES}, "C0")


@pytest.fixture(scope="module")
def rig_from_world() -> Rigid3:
    # nadir-looking rig at ~1500 m above a world frame with z up, arbitrary heading and some tilt
    R = (Rotation.from_euler("xyz", [np.pi + 0.02, -0.015, 0.7])).as_matrix()
    centre = np.array([1234.5, -678.9, 1500.0])
    return Rigid3(R, -R @ centre)


def points_seen_by(rig: Rig, name: str, rig_from_world: Rigid3, n: int, seed: int):
    """World points (n, 3) inside the view of camera `name`, their camera-frame coordinates and
    the undistorted pixels, computed with the pinhole model (not with the library's unproject)."""
    rng = np.random.default_rng(seed)
    camera = rig.cameras[name]
    u = rng.uniform(0, camera.width - 1, n)
    v = rng.uniform(0, camera.height - 1, n)
    depth = rng.uniform(800.0, 3000.0, n)
    points_cam = np.column_stack([(u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy, np.ones(n)]) * depth[:, None]
    world_from_cam = (rig.cam_from_rig[name] * rig_from_world).inverse()
    return world_from_cam.apply(points_cam), points_cam, np.column_stack([u, v])


# ------------------------------------------------------------------------------ the rig itself


def test_rig_layout_matches_the_paper(rig):
    np.testing.assert_allclose(rig.camera_center("C0"), 0.0, atol=1e-15)
    for name in EULER_DEG:
        np.testing.assert_allclose(rig.camera_center(name), CENTRES[name], atol=1e-15)
        # optical axes of C1..C4 are tilted ~45 deg from C0's
        axis = rig.cam_from_rig[name].R.T @ np.array([0.0, 0.0, 1.0])
        tilt = np.degrees(np.arccos(axis[2]))
        assert 43.5 < tilt < 46.5
    assert rig.camera_names == NAMES
    assert rig.reference_camera == "C0"


def test_rig_project_is_camera_project_of_cam_from_world(rig, rig_from_world):
    for k, name in enumerate(NAMES):
        points_world, points_cam, undistorted = points_seen_by(rig, name, rig_from_world, 50, seed=k)
        uv = rig.project(name, rig_from_world, points_world)
        np.testing.assert_allclose(uv, rig.cameras[name].project(points_cam), rtol=0, atol=1e-6)
        np.testing.assert_allclose(uv, rig.cameras[name].distort(undistorted), rtol=0, atol=1e-6)
        assert np.isfinite(uv).all()


def test_rig_project_sees_nothing_of_other_cameras_view(rig, rig_from_world):
    """The views do not overlap: C0's points are behind or far outside the tilted cameras' images."""
    points_world, _, _ = points_seen_by(rig, "C0", rig_from_world, 100, seed=99)
    for name in EULER_DEG:
        uv = rig.project(name, rig_from_world, points_world)
        assert not rig.cameras[name].in_image(np.nan_to_num(uv, nan=-1e9)).any()


# --------------------------------------------------------------------------- generalized rays


@pytest.mark.parametrize("name", NAMES)
def test_rays_satisfy_the_generalized_projection_equation(rig, rig_from_world, name):
    """alpha f + v = R M + t with alpha > 0, v = camera centre in the rig frame, |f| = 1."""
    points_world, points_cam, _ = points_seen_by(rig, name, rig_from_world, 200, seed=10 + NAMES.index(name))
    uv = rig.project(name, rig_from_world, points_world)
    origins, directions = rig.rays(name, uv)
    assert origins.shape == directions.shape == (200, 3)
    np.testing.assert_allclose(origins, np.broadcast_to(rig.camera_center(name), origins.shape), atol=1e-15)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0, atol=1e-14)

    points_rig = rig_from_world.apply(points_world)  # R M + t
    to_point = points_rig - origins
    distance = np.linalg.norm(to_point, axis=1)
    np.testing.assert_allclose(np.cross(directions, to_point / distance[:, None]), 0.0, atol=1e-11)
    alpha = np.einsum("ij,ij->i", directions, to_point)
    assert (alpha > 0).all()
    np.testing.assert_allclose(alpha, distance, rtol=1e-12)
    np.testing.assert_allclose(alpha[:, None] * directions + origins, points_rig, rtol=0, atol=1e-6)
    # the depth along the ray is the distance from the camera centre to the point
    np.testing.assert_allclose(alpha, np.linalg.norm(points_cam, axis=1), rtol=1e-9)


@pytest.mark.parametrize("name", NAMES)
def test_ray_direction_is_R_c_K_inverse_undistorted_pixel(rig, rig_from_world, name):
    """f = R_c K_c^-1 m~ (normalised), R_c the rotation of rig_from_cam, m~ the undistorted pixel."""
    points_world, _, undistorted = points_seen_by(rig, name, rig_from_world, 100, seed=20 + NAMES.index(name))
    camera = rig.cameras[name]
    uv = rig.project(name, rig_from_world, points_world)
    _, directions = rig.rays(name, uv)
    R_c = rig_from_cam(name).R
    t_c = np.array(CENTRES.get(name, (0.0, 0.0, 0.0)))
    for m_undistorted in (undistorted, camera.undistort(uv)):
        m_tilde = np.column_stack([m_undistorted, np.ones(len(m_undistorted))])
        f = (R_c @ np.linalg.inv(camera.K) @ m_tilde.T).T
        f /= np.linalg.norm(f, axis=1, keepdims=True)
        np.testing.assert_allclose(directions, f, rtol=0, atol=1e-12)
    origins, _ = rig.rays(name, uv)
    np.testing.assert_allclose(origins, np.broadcast_to(t_c, origins.shape), atol=1e-15)  # v = t_c


def test_rays_of_mixed_cameras_equals_per_camera_rays(rig, rig_from_world):
    names, pixels = [], []
    for k, name in enumerate(NAMES):
        points_world, _, _ = points_seen_by(rig, name, rig_from_world, 20 + k, seed=30 + k)
        names += [name] * len(points_world)
        pixels.append(rig.project(name, rig_from_world, points_world))
    names = np.array(names)
    pixels = np.vstack(pixels)
    order = np.random.default_rng(31).permutation(len(names))
    names, pixels = names[order], pixels[order]

    origins, directions = rig.rays_of(list(names), pixels)
    assert origins.shape == directions.shape == (len(names), 3)
    for name in NAMES:
        mask = names == name
        expected_origins, expected_directions = rig.rays(name, pixels[mask])
        np.testing.assert_array_equal(origins[mask], expected_origins)
        np.testing.assert_array_equal(directions[mask], expected_directions)
    # a single camera name and an empty set also work
    o1, d1 = rig.rays_of(["C3"], pixels[:1])
    np.testing.assert_array_equal(d1, rig.rays("C3", pixels[:1])[1])
    o0, d0 = rig.rays_of([], np.zeros((0, 2)))
    assert o0.shape == d0.shape == (0, 3)


def test_unknown_camera_raises_naming_it(rig, rig_from_world):
    uv = np.array([[100.0, 200.0], [300.0, 400.0]])
    with pytest.raises(DmaisError, match="C9"):
        rig.rays_of(["C0", "C9"], uv)
    with pytest.raises(DmaisError, match="C7"):
        rig.rays("C7", uv)
    with pytest.raises(DmaisError, match="C7"):
        rig.project("C7", rig_from_world, np.zeros((1, 3)))
    with pytest.raises(DmaisError, match="C7"):
        rig.camera_center("C7")
    with pytest.raises(DmaisError, match="2 camera names for 3 pixels"):
        rig.rays_of(["C0", "C1"], np.zeros((3, 2)))


def test_inconsistent_rig_raises(rig):
    with pytest.raises(DmaisError):
        Rig(dict(rig.cameras), {k: v for k, v in rig.cam_from_rig.items() if k != "C4"}, "C0")
    with pytest.raises(DmaisError, match="C5"):
        Rig(dict(rig.cameras), dict(rig.cam_from_rig), "C5")


# ------------------------------------------------------------------------------- serialization


def assert_same_rig(a: Rig, b: Rig) -> None:
    assert a.reference_camera == b.reference_camera
    assert a.camera_names == b.camera_names
    for name in a.camera_names:
        assert a.cameras[name] == b.cameras[name]
        np.testing.assert_array_equal(a.cam_from_rig[name].R, b.cam_from_rig[name].R)
        np.testing.assert_array_equal(a.cam_from_rig[name].t, b.cam_from_rig[name].t)


def test_to_dict_layout_and_round_trip(rig):
    data = rig.to_dict()
    assert data["reference_camera"] == "C0"
    assert [entry["name"] for entry in data["cameras"]] == NAMES
    for entry in data["cameras"]:
        assert set(entry) == {"name", "width", "height", "fx", "fy", "cx", "cy", "d", "cam_from_rig"}
        assert set(entry["cam_from_rig"]) == {"R", "t"}
        assert np.shape(entry["cam_from_rig"]["R"]) == (3, 3)
        assert np.shape(entry["cam_from_rig"]["t"]) == (3,)
        name = entry["name"]
        fx, fy, cx, cy, d = INTRINSICS[name]
        assert (entry["fx"], entry["fy"], entry["cx"], entry["cy"], entry["d"]) == (fx, fy, cx, cy, d)
        assert (entry["width"], entry["height"]) == (4096, 3000)
        np.testing.assert_array_equal(entry["cam_from_rig"]["R"], rig.cam_from_rig[name].R)
    assert_same_rig(Rig.from_dict(json.loads(json.dumps(data))), rig)


def test_save_load_round_trip(rig, tmp_path):
    path = tmp_path / "results" / "rig.json"
    written = rig.save(path, eps_calib_px=0.25, note="synthetic")
    assert written == path and path.exists()
    assert sorted(p.name for p in path.parent.iterdir()) == ["rig.json"]  # no temporary left over
    data = json.loads(path.read_text())
    assert data["reference_camera"] == "C0"
    assert data["eps_calib_px"] == 0.25 and data["note"] == "synthetic"
    assert [entry["name"] for entry in data["cameras"]] == NAMES
    loaded = Rig.load(path)
    assert_same_rig(loaded, rig)
    # the loaded rig gives the same rays (to rounding: memory layouts of R differ after loading)
    uv = np.array([[10.0, 20.0], [2048.0, 1500.0], [4095.0, 2999.0]])
    for name in NAMES:
        for got, expected in zip(loaded.rays(name, uv), rig.rays(name, uv)):
            np.testing.assert_allclose(got, expected, rtol=1e-15, atol=1e-16)


def test_load_errors_name_the_file(tmp_path):
    missing = tmp_path / "missing.json"
    with pytest.raises(DmaisError, match="missing.json"):
        Rig.load(missing)
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    with pytest.raises(DmaisError, match="broken.json"):
        Rig.load(broken)
    incomplete = tmp_path / "incomplete.json"
    incomplete.write_text(json.dumps({"reference_camera": "C0", "cameras": [{"name": "C0", "fx": 1.0}]}))
    with pytest.raises(DmaisError, match="incomplete.json"):
        Rig.load(incomplete)
