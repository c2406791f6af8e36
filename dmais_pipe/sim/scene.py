"""The simulated world: truth rig, 3D calibration field, camera poses, flight sites and frames.

World frame: local east-north-up, metres. Everything here is ground truth; the noise that a
dataset's measurements carry is added by `sim.simulate`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from ..camera import Camera
from ..geometry import Rigid3, exp_so3, rotation_from_euler_zyx
from ..rig import Rig
from .config import LENS_COEFFICIENTS, check_camera_entry, check_flight_pattern
from .render import MarkerBoard


@dataclass
class Marker:
    """A board in the world and the ids of its X-corners (in `board.corners()` order)."""

    board: MarkerBoard
    point_ids: list[str]
    group: str  # field region ("L", "C", "R") or flight site

    @property
    def normal(self) -> np.ndarray:
        return np.cross(self.board.axis_u, self.board.axis_v)


@dataclass
class Shot:
    """One simulated image: which camera, where, and what for."""

    image: str
    camera: str
    stage: str
    cam_from_world: Rigid3
    split: str = ""
    placement: str = ""


@dataclass
class Frame:
    """One flight frame: rig pose, and each camera's in-flight cam_from_rig (mount deviation)."""

    frame: str
    group: str
    site: str
    rig_from_world: Rigid3
    cam_from_rig: dict[str, Rigid3]


def build_rig(config: dict) -> Rig:
    """Truth rig from the `rig` settings (intrinsics, rig_from_cam Euler angles and centres)."""
    cameras, cam_from_rig = {}, {}
    for name, c in config["cameras"].items():
        cameras[name] = rig_camera(name, c, config["width"], config["height"])
        rig_from_cam = Rigid3(rotation_from_euler_zyx(np.radians(c["euler_zyx_deg"])), c["center_m"])
        cam_from_rig[name] = rig_from_cam.inverse()
    return Rig(cameras, cam_from_rig, config["reference_camera"])


def rig_camera(name: str, entry: dict, width: int, height: int) -> Camera:
    """The truth Camera of one `rig.cameras` entry (`check_camera_entry`): fx, fy, cx, cy and, by its
    `model` (default radial1), d (radial1) or k1, k2, p1, p2, k3 (opencv, any left out is 0)."""
    model = check_camera_entry(name, entry)
    if model == "radial1":
        return Camera(entry["fx"], entry["fy"], entry["cx"], entry["cy"], entry["d"], width, height)
    k1, k2, p1, p2, k3 = (float(entry.get(key, 0.0)) for key in LENS_COEFFICIENTS[model])
    return Camera(entry["fx"], entry["fy"], entry["cx"], entry["cy"], k1, width, height, model, k2=k2, p1=p1,
                  p2=p2, k3=k3)


def look_rotation(forward, down_hint=(0.0, 0.0, -1.0)) -> np.ndarray:
    """world_from_cam rotation (3, 3) of a camera looking along `forward`, image y towards `down_hint`."""
    z = np.asarray(forward, dtype=float)
    z = z / np.linalg.norm(z)
    y = np.asarray(down_hint, dtype=float) - z * np.dot(down_hint, z)
    y /= np.linalg.norm(y)
    return np.column_stack([np.cross(y, z), y, z])


def direction(azimuth_deg: float, elevation_deg: float = 0.0) -> np.ndarray:
    """Unit vector at an azimuth clockwise from north (+y) and an elevation above the horizon."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    return np.array([np.sin(az) * np.cos(el), np.cos(az) * np.cos(el), np.sin(el)])


def small_rotation(rng: np.random.Generator, sigma_rad: float) -> np.ndarray:
    """(3, 3) rotation by a rotation vector with N(0, sigma^2) components."""
    return exp_so3(rng.normal(0.0, sigma_rad, 3))


# --------------------------------------------------------------------------- calibration field


def build_field(config: dict, rng: np.random.Generator) -> list[Marker]:
    """Vertical 2 m markers and 3 m six-corner boards in three regions in front of the station.

    Markers sit one per cell of an azimuth/elevation grid seen from the station, so none hides
    another; their distances vary over `distance_m` so that the field is far from coplanar.
    Boards go to the middle row, where they can stand far enough to fit in one cell.
    """
    f = config["field"]
    station = np.asarray(f["station_m"], dtype=float)
    azimuths = np.arange(-f["region_half_width_deg"] + f["cell_deg"] / 2, f["region_half_width_deg"], f["cell_deg"])
    elevations = np.asarray(f["row_elevation_deg"], dtype=float)
    markers = []
    for region_azimuth, region in zip(f["region_azimuth_deg"], f["region_names"]):
        middle = [(a, 0.0) for a in azimuths]
        boards = {middle[k] for k in rng.choice(len(middle), size=min(f["boards_per_region"], len(middle)), replace=False)}
        count = {"marker": 0, "board": 0}
        for d_az in azimuths:
            for elevation in elevations:
                kind = "board" if (d_az, elevation) in boards else "marker"
                count[kind] += 1
                markers.append(_field_marker(config, rng, station, region_azimuth + d_az, elevation, region, kind,
                                             count[kind]))
    return markers


def _field_marker(config, rng, station, azimuth, elevation, region, kind, number) -> Marker:
    f = config["field"]
    near, far = f["distance_m"]
    if kind == "board":
        near = max(near, f["board_min_distance_m"])
        half_height = f["board_size_m"][1] / 2
    else:
        half_height = config["marker_size_m"] / 2
    # The distance range along this line of sight keeps the whole board inside `height_m`.
    low, high = f["height_m"][0] + half_height - station[2], f["height_m"][1] - half_height - station[2]
    tan_el = np.tan(np.radians(elevation))
    if tan_el > 0:
        far = min(far, high / tan_el)
    elif tan_el < 0:
        far = min(far, low / tan_el)
    if far < near:
        raise ValueError(f"field row at {elevation} deg elevation cannot hold a {kind} within height_m")
    distance = rng.uniform(near, far)
    ground = direction(azimuth) * distance
    center = np.array([station[0] + ground[0], station[1] + ground[1], station[2] + distance * tan_el])
    facing = -direction(azimuth + rng.uniform(-f["facing_yaw_deg"], f["facing_yaw_deg"]))
    axis_u = np.cross([0.0, 0.0, 1.0], facing)  # horizontal, along the board
    axis_u /= np.linalg.norm(axis_u)
    axis_v = np.array([0.0, 0.0, -1.0])  # rows go down
    polarity = int(rng.choice([-1, 1]))
    if kind == "board":
        cols, rows = f["board_cells"]
        width, height = f["board_size_m"]
        board = MarkerBoard(center, axis_u, axis_v, cols, rows, width / cols, height / rows, polarity)
        ids = [f"{region}B{number}-{k}" for k in range((cols - 1) * (rows - 1))]
    else:
        cell = config["marker_size_m"] / 2
        board = MarkerBoard(center, axis_u, axis_v, 2, 2, cell, cell, polarity)
        ids = [f"{region}{number:02d}"]
    return Marker(board, ids, region)


# ------------------------------------------------------------------------------ visibility


def visible_points(camera: Camera, cam_from_world: Rigid3, markers: list[Marker], margin_px: float,
                   min_cos: float = 0.25) -> list[tuple[str, np.ndarray, float]]:
    """(point id, distorted pixel (2,), apparent marker size in px) of corners seen by a camera.

    A corner is seen when it is in front, at least `margin_px` inside the image, and its board
    faces the camera with |cos(incidence)| >= min_cos.
    """
    seen = []
    center = cam_from_world.center
    for marker in in_view_cone(camera, cam_from_world, markers):
        corners = marker.board.corners()
        cam_points = cam_from_world.apply(corners)
        uv = camera.project(cam_points)
        to_camera = center - corners
        cos = np.abs(to_camera @ marker.normal) / np.linalg.norm(to_camera, axis=1)
        size_px = camera.fx * 2 * max(marker.board.cell_u, marker.board.cell_v) / np.maximum(cam_points[:, 2], 1e-9)
        ok = (cam_points[:, 2] > 0) & camera.in_image(np.nan_to_num(uv, nan=-1e9), margin_px) & (cos >= min_cos)
        for k in np.flatnonzero(ok):
            seen.append((marker.point_ids[k], uv[k], float(size_px[k])))
    return seen


def in_view_cone(camera: Camera, cam_from_world: Rigid3, markers: list[Marker]) -> list[Marker]:
    """The markers (in their order) whose board may reach into the image: centre within twice the
    widest angle of the image's corners from the optical axis, widened by the board's angular radius.
    A cheap preselection, not a test: a marker left out has no corner in the image."""
    corners = np.array([[-0.5, -0.5], [camera.width - 0.5, -0.5], [-0.5, camera.height - 0.5],
                        [camera.width - 0.5, camera.height - 0.5]])
    widest = 2.0 * np.max(np.arccos(np.clip(camera.unproject(corners)[:, 2], -1.0, 1.0)))
    if not markers or not np.isfinite(widest) or widest >= np.pi / 2:
        return markers
    centres = cam_from_world.apply(np.array([m.board.origin for m in markers]))  # (M, 3)
    radius = np.array([np.hypot(*m.board.half_size) + m.board.margin for m in markers])  # (M,)
    distance = np.linalg.norm(centres, axis=1)
    off_axis = np.arctan2(np.hypot(centres[:, 0], centres[:, 1]), centres[:, 2])
    reach = np.arcsin(np.clip(radius / np.maximum(distance, 1e-12), 0.0, 1.0))
    keep = (distance <= radius) | (off_axis <= widest + reach)
    return [marker for marker, kept in zip(markers, keep) if kept]


# ------------------------------------------------------------------------------ calibration shots


def intrinsic_shots(config: dict, rig: Rig, markers: list[Marker], rng: np.random.Generator) -> list[Shot]:
    """Per camera, images of the field from several orientations (aim, roll), split calib/eval."""
    c = config["intrinsics"]
    f = config["field"]
    station = np.asarray(f["station_m"], dtype=float)
    shots = []
    for name, camera in rig.cameras.items():
        n_calib, n_eval = c["calib_images_per_camera"], c["eval_images_per_camera"]
        for k in range(n_calib + n_eval):
            split = "calib" if k < n_calib else "eval"
            cam_from_world = _intrinsic_pose(config, camera, station, markers, rng)
            shots.append(Shot(f"intr_{name}_{k:03d}", name, "intrinsics", cam_from_world, split=split))
    return shots


def _intrinsic_pose(config, camera, station, markers, rng) -> Rigid3:
    c, f = config["intrinsics"], config["field"]
    for _ in range(200):
        azimuth = rng.choice(f["region_azimuth_deg"]) + rng.uniform(-1, 1) * c["aim_jitter_deg"][0]
        elevation = rng.uniform(-1, 1) * c["aim_jitter_deg"][1]
        roll = np.radians(90.0 * rng.integers(4) + rng.normal(0.0, c["roll_jitter_deg"]))
        forward = direction(azimuth, elevation)
        world_from_cam = look_rotation(forward) @ exp_so3([0, 0, roll])
        position = station + rng.normal(0.0, c["station_jitter_m"], 3)
        cam_from_world = Rigid3(world_from_cam, position).inverse()
        if len(visible_points(camera, cam_from_world, markers, 20.0)) >= c["min_points"]:
            return cam_from_world
    raise RuntimeError("could not find an intrinsic-calibration view seeing enough markers")


def placement_poses(config: dict, rig: Rig, rng: np.random.Generator) -> list[Rigid3]:
    """rig_from_world of each extrinsic placement: the rig turned 90 deg about C0's axis each time.

    After each turn the operator makes a minor adjustment so that the horizontal cameras look at
    the field regions: the small rotation that best aligns their axes with the regions.
    """
    f, e = config["field"], config["extrinsics"]
    station = np.asarray(f["station_m"], dtype=float)
    world_from_rig0 = look_rotation(direction(0.0))
    targets = [direction(a) for a in f["region_azimuth_deg"]]
    poses = []
    for j in range(e["placements"]):
        roll = np.radians(e["initial_roll_deg"] + 90.0 * j)
        world_from_rig = world_from_rig0 @ exp_so3([0, 0, roll])
        world_from_rig = _adjust_to_field(rig, world_from_rig, targets) @ world_from_rig
        world_from_rig = small_rotation(rng, np.radians(e["adjust_jitter_deg"])) @ world_from_rig
        position = station + rng.normal(0.0, e["station_jitter_m"], 3)
        poses.append(Rigid3(world_from_rig, position).inverse())
    return poses


def horizontal_cameras(rig: Rig, world_from_rig_R: np.ndarray, max_elevation_deg: float = 20.0) -> list[str]:
    """Cameras whose optical axis is within `max_elevation_deg` of the horizon."""
    names = []
    for name, cam_from_rig in rig.cam_from_rig.items():
        axis = world_from_rig_R @ cam_from_rig.R.T[:, 2]
        if abs(np.degrees(np.arcsin(np.clip(axis[2], -1, 1)))) <= max_elevation_deg:
            names.append(name)
    return names


def _adjust_to_field(rig: Rig, world_from_rig_R: np.ndarray, targets: list[np.ndarray]) -> np.ndarray:
    axes, goals = [], []
    for name in horizontal_cameras(rig, world_from_rig_R):
        axis = world_from_rig_R @ rig.cam_from_rig[name].R.T[:, 2]
        axes.append(axis)
        goals.append(max(targets, key=lambda target: float(target @ axis)))
    if len(axes) < 2:
        return np.eye(3)
    adjustment, _ = Rotation.align_vectors(np.array(goals), np.array(axes))
    return adjustment.as_matrix()


# ------------------------------------------------------------------------------------ flights


def terrain_height(config: dict, site_center: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Ground height (n,) at world xy (n, 2) of a site: a gentle smooth undulation."""
    a = config["flight"]["terrain_amplitude_m"]
    dx, dy = (xy - site_center[:2]).T
    return site_center[2] + a * (np.sin(dx / 97.0) * np.cos(dy / 131.0) + 0.5 * np.sin((dx + dy) / 211.0))


def nominal_rig_pose(config: dict, site_center: np.ndarray, rng: np.random.Generator) -> Rigid3:
    """rig_from_world of a hovering rig: C0 straight down, random heading, `altitude_m` up."""
    fl = config["flight"]
    heading = rng.uniform(0.0, 360.0)
    world_from_rig = look_rotation([0.0, 0.0, -1.0], down_hint=-direction(heading))
    offset = rng.uniform(-1, 1, 2) * fl["group_offset_m"]
    xy = site_center[:2] + offset
    ground = terrain_height(config, site_center, xy[None])[0]
    position = np.array([xy[0], xy[1], ground + fl["altitude_m"] + rng.normal(0.0, fl["altitude_jitter_m"])])
    return Rigid3(world_from_rig, position).inverse()


def ground_markers_for(config: dict, rig: Rig, rig_from_world: Rigid3, site: str, site_center: np.ndarray,
                       rng: np.random.Generator, existing: list[Marker]) -> list[Marker]:
    """Flat 2 m markers on the terrain, `markers_per_camera` inside each camera's footprint.

    New markers' centres stay 2.5 marker sizes from each other and from the site's `existing`
    markers, so that no two boards overlap whatever their spin. Ids number the site's markers:
    G<site><len(existing) + 1 ...>.
    """
    fl = config["flight"]
    taken = np.array([m.board.origin for m in existing]).reshape(-1, 3)  # (n, 3) centres
    min_gap = 2.5 * config["marker_size_m"]
    markers = []
    for name, camera in rig.cameras.items():
        cam_from_world = rig.cam_from_rig[name] * rig_from_world
        placed = []
        for _ in range(fl["markers_per_camera"] * 50):
            if len(placed) == fl["markers_per_camera"]:
                break
            uv = _random_pixel(camera, fl["marker_margin_frac"], rng)
            point = _terrain_hit(config, site_center, cam_from_world, camera, uv)
            size_px = camera.fx * config["marker_size_m"] / np.linalg.norm(point - cam_from_world.center)
            apart = all(np.hypot(*(uv - other)) > 3.0 * size_px for other in placed)
            if apart and np.all(np.linalg.norm(taken - point, axis=1) > min_gap):
                placed.append(uv)
                taken = np.vstack([taken, point])
                index = len(existing) + len(markers) + 1
                markers.append(_ground_marker(config, site, site_center, point, rng, f"G{site}{index:03d}"))
    return markers


def _random_pixel(camera: Camera, margin_frac: float, rng) -> np.ndarray:
    mx, my = margin_frac * camera.width, margin_frac * camera.height
    return np.array([rng.uniform(mx, camera.width - mx), rng.uniform(my, camera.height - my)])


def _terrain_hit(config, site_center, cam_from_world: Rigid3, camera: Camera, uv) -> np.ndarray:
    """World point where the ray of pixel uv meets the terrain (fixed-point on the height, at most 20
    iterations; once the height repeats exactly, further ones would change nothing)."""
    world_from_cam = cam_from_world.inverse()
    ray = world_from_cam.R @ camera.unproject(uv)[0]
    origin = world_from_cam.t
    height = site_center[2]
    for _ in range(20):
        point = origin + ray * (height - origin[2]) / ray[2]
        height, previous = terrain_height(config, site_center, point[None, :2])[0], height
        if height == previous:
            break
    return origin + ray * (height - origin[2]) / ray[2]


def _ground_marker(config, site, site_center, point, rng, point_id) -> Marker:
    eps = 0.5
    h = lambda dx, dy: terrain_height(config, site_center, (point[:2] + [dx, dy])[None])[0]  # noqa: E731
    normal = np.array([-(h(eps, 0) - h(-eps, 0)) / (2 * eps), -(h(0, eps) - h(0, -eps)) / (2 * eps), 1.0])
    normal /= np.linalg.norm(normal)
    spin = rng.uniform(0.0, 2 * np.pi)
    axis_u = np.array([np.cos(spin), np.sin(spin), 0.0])
    axis_u -= normal * (axis_u @ normal)
    axis_u /= np.linalg.norm(axis_u)
    axis_v = np.cross(normal, axis_u)
    cell = config["marker_size_m"] / 2
    board = MarkerBoard(point, axis_u, axis_v, 2, 2, cell, cell, int(rng.choice([-1, 1])))
    return Marker(board, [point_id], site)


def line_poses(config: dict, nominal: Rigid3) -> list[Rigid3]:
    """rig_from_world of each of a group's `frames_per_group` frames on a straight line through its
    `nominal` pose, in the direction of its heading (C0's image up): frame k at (k - (F - 1) / 2) x
    `line_spacing_m` along it, with the nominal attitude and height."""
    fl = config["flight"]
    world_from_nominal = nominal.inverse()
    heading = -world_from_nominal.R[:, 1]  # C0 looks down with its image's y axis away from the heading
    steps = (np.arange(fl["frames_per_group"]) - (fl["frames_per_group"] - 1) / 2) * fl["line_spacing_m"]
    return [Rigid3(world_from_nominal.R, world_from_nominal.t + step * heading).inverse() for step in steps]


def flight_frames(config: dict, rig: Rig, rng: np.random.Generator) -> tuple[list[Frame], list[Marker]]:
    """The frames of every group, with the sites' ground markers. Per `flight.pattern`: "hover", every
    frame around the group's nominal pose, markers placed once for it; "line", frame k around
    `line_poses`[k], markers placed for every frame's pose in turn (after the earlier frames')."""
    pattern = check_flight_pattern(config)
    fl = config["flight"]
    frames, markers = [], []
    for site, spec in fl["sites"].items():
        site_center = np.asarray(spec["center_m"], dtype=float)
        for group in spec["groups"]:
            nominal = nominal_rig_pose(config, site_center, rng)
            poses = [nominal] * fl["frames_per_group"] if pattern == "hover" else line_poses(config, nominal)
            placements = poses[:1] if pattern == "hover" else poses  # the poses that markers are placed for
            for pose in placements:
                site_markers = [m for m in markers if m.group == site]
                markers += ground_markers_for(config, rig, pose, site, site_center, rng, site_markers)
            frames += _group_frames(config, rig, poses, site, str(group), rng)
    return frames, markers


def _group_frames(config, rig: Rig, nominals: list[Rigid3], site: str, group: str, rng) -> list[Frame]:
    """The group's frames, frame k jittered around nominals[k] (rig_from_world), with the group's
    mounting change and each frame's vibration."""
    fl = config["flight"]
    arcmin = np.radians(1.0 / 60.0)
    # The rig frame is the reference camera's, so only the other cameras move relative to it.
    others = [name for name in rig.cam_from_rig if name != rig.reference_camera]
    mount = {
        name: Rigid3(small_rotation(rng, fl["mount_sigma_arcmin"] * arcmin), np.zeros(3)) * rig.cam_from_rig[name]
        for name in others
    }
    frames = []
    for k, nominal in enumerate(nominals):
        world_from_nominal = nominal.inverse()
        R = small_rotation(rng, np.radians(fl["hover_attitude_sigma_deg"])) @ world_from_nominal.R
        t = world_from_nominal.t + rng.normal(0.0, fl["hover_position_sigma_m"], 3)
        cam_from_rig = {rig.reference_camera: rig.cam_from_rig[rig.reference_camera]}
        for name, pose in mount.items():
            cam_from_rig[name] = Rigid3(small_rotation(rng, fl["vibration_sigma_arcmin"] * arcmin), np.zeros(3)) * pose
        frames.append(Frame(f"g{group}_f{k:03d}", group, site, Rigid3(R, t).inverse(), cam_from_rig))
    return frames
