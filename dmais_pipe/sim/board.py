"""A flat calibration board seen by a few cameras: synthetic truth for the planar calibration.

An asymmetric circle grid (OpenCV's pattern: rows of `columns` centres, every other row shifted by
half a period; 11 x 8 = 88 points) on the plane z = 0 of the world frame, and views of it with
seeded noise: each camera's own views (a `fronto_fraction` of them 1-4 deg from parallel to the
image plane, the others tilted by 15-45 deg, as people hold a board), and placements of a rig
(cam_from_rig per camera) whose board pose two or more cameras see whole. `write_board_dataset`
writes them as a dataset: every view an intrinsics image (calib, or eval for the last
`eval_views` of each camera), every shared view also an extrinsics image of its placement.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from scipy.spatial.transform import Rotation

from ..camera import Camera
from ..geometry import Rigid3

#: Pixels a board's points keep from the image border (a detector needs the whole board).
BORDER_PX = 10.0
FRONTO_TILT_DEG = (1.0, 4.0)
TILT_RANGE_DEG = (15.0, 45.0)


@dataclass
class BoardView:
    """One image of the board: its camera, placement ('' for a camera's own view), true
    cam_from_world and the noisy pixels (n, 2) of every board point."""

    camera: str
    placement: str
    cam_from_world: Rigid3
    pixels: np.ndarray


@dataclass
class BoardScene:
    """The board's points (n, 3), the true cameras and cam_from_rig, and the views."""

    points: np.ndarray
    cameras: dict[str, Camera]
    cam_from_rig: dict[str, Rigid3]
    views: dict[str, BoardView] = field(default_factory=dict)


def asymmetric_circle_grid(rows: int = 11, columns: int = 8, spacing_m: float = 0.02) -> np.ndarray:
    """(rows * columns, 3) the centres of an asymmetric circle grid on z = 0: row i at y = i s / 2,
    its centres at x = (2 j + i mod 2) s / 2 (OpenCV's CALIB_CB_ASYMMETRIC_GRID layout)."""
    i, j = np.meshgrid(np.arange(rows), np.arange(columns), indexing="ij")
    x = (2 * j + i % 2) * spacing_m / 2.0
    return np.column_stack([x.ravel(), (i * spacing_m / 2.0).ravel(), np.zeros(i.size)])


def board_pose(camera: Camera, points: np.ndarray, tilt_deg: float, rng: np.random.Generator,
               tries: int = 200) -> Rigid3 | None:
    """A cam_from_world placing the whole board in `camera`'s image, tilted by `tilt_deg` about a
    random axis of the image plane and turned by up to 30 deg about the optical axis; None when no
    try fits."""
    centre = points.mean(axis=0)
    extent = np.ptp(points, axis=0).max()
    for _ in range(tries):
        axis = rng.uniform(0.0, 2.0 * np.pi)
        tilt = Rotation.from_rotvec(np.radians(tilt_deg) * np.array([np.cos(axis), np.sin(axis), 0.0]))
        R = (tilt * Rotation.from_euler("z", rng.uniform(-30.0, 30.0), degrees=True)).as_matrix()
        depth = camera.fx * extent / rng.uniform(0.3, 0.75) / camera.width  # the board spans 30-75% of the width
        lateral = rng.uniform(-0.25, 0.25, 2) * depth * np.array([camera.width / camera.fx, camera.height / camera.fy])
        pose = Rigid3(R, np.array([*lateral, depth]) - R @ centre)
        if sees_whole_board(camera, pose, points):
            return pose
    return None


def sees_whole_board(camera: Camera, cam_from_world: Rigid3, points: np.ndarray) -> bool:
    """Whether every point (n, 3) of the board projects at least BORDER_PX inside the image."""
    uv = camera.project(cam_from_world.apply(points))
    return bool(np.isfinite(uv).all() and camera.in_image(uv, margin=BORDER_PX).all())


def board_scene(cameras: dict[str, Camera], cam_from_rig: dict[str, Rigid3], views_per_camera: int,
                placements: int, seed: int, noise_px: float = 0.15, fronto_fraction: float = 0.5) -> BoardScene:
    """Each camera's `views_per_camera` own views and `placements` rig placements (the first camera
    and at least one other seeing the whole board), pixels with Gaussian noise of `noise_px` per axis."""
    rng = np.random.default_rng(seed)
    scene = BoardScene(asymmetric_circle_grid(), dict(cameras), dict(cam_from_rig))
    for name, camera in cameras.items():
        for k in range(views_per_camera):
            tilt = rng.uniform(*FRONTO_TILT_DEG) if k < fronto_fraction * views_per_camera \
                else rng.uniform(*TILT_RANGE_DEG)
            pose = board_pose(camera, scene.points, tilt, rng)
            if pose is not None:
                _add_view(scene, f"{name}_v{k:02d}", name, "", pose, noise_px, rng)
    reference = next(iter(cameras))
    made = 0
    while made < placements:
        tilt = rng.uniform(*FRONTO_TILT_DEG) if rng.uniform() < fronto_fraction else rng.uniform(*TILT_RANGE_DEG)
        ref_pose = board_pose(cameras[reference], scene.points, tilt, rng)
        if ref_pose is None:
            continue
        rig_from_world = cam_from_rig[reference].inverse() * ref_pose
        seeing = [c for c in cameras if sees_whole_board(cameras[c], cam_from_rig[c] * rig_from_world, scene.points)]
        if len(seeing) < 2:
            continue
        for name in seeing:
            _add_view(scene, f"{name}_p{made:02d}", name, f"p{made:02d}", cam_from_rig[name] * rig_from_world,
                      noise_px, rng)
        made += 1
    return scene


def _add_view(scene: BoardScene, image: str, camera: str, placement: str, pose: Rigid3, noise_px: float,
              rng: np.random.Generator) -> None:
    uv = scene.cameras[camera].project(pose.apply(scene.points))
    scene.views[image] = BoardView(camera, placement, pose, uv + rng.normal(scale=noise_px, size=uv.shape))


def point_ids(points: np.ndarray) -> list[str]:
    """The board points' ids, b00, b01, ..."""
    return [f"b{k:02d}" for k in range(len(points))]


def write_board_dataset(scene: BoardScene, root: Path, eval_views: int = 3, focal_px: bool = False) -> Path:
    """The scene as a dataset of observations (no image files): every view an intrinsics image (the
    last `eval_views` of each camera's eval), every placement's view also an extrinsics image; the
    cameras' dataset.yaml model is their own, focal_px their true fx when `focal_px`."""
    from ..dataset import write_dataset

    ids = point_ids(scene.points)
    images, observations = [], []
    for name in scene.cameras:
        own = [image for image, view in scene.views.items() if view.camera == name]
        for k, image in enumerate(own):
            images.append({"image": image, "camera": name, "stage": "intrinsics",
                           "split": "eval" if k >= len(own) - eval_views else "calib", "placement": "", "path": ""})
            observations.append(_observations(image, ids, scene.views[image].pixels))
    for image, view in scene.views.items():
        if view.placement:
            images.append({"image": f"x_{image}", "camera": view.camera, "stage": "extrinsics", "split": "",
                           "placement": view.placement, "path": ""})
            observations.append(_observations(f"x_{image}", ids, view.pixels))
    points = pd.DataFrame(scene.points, columns=["x", "y", "z"], index=pd.Index(ids, name="point_id"))
    cameras = {name: {"width": c.width, "height": c.height, "model": c.model, **({"focal_px": c.fx} if focal_px else {})}
               for name, c in scene.cameras.items()}
    manifest = {"name": "board", "reference_camera": next(iter(scene.cameras)), "cameras": cameras}
    write_dataset(root, manifest, points, pd.DataFrame(images), observations=pd.concat(observations, ignore_index=True))
    return Path(root)


def _observations(image: str, ids: list[str], pixels: np.ndarray) -> pd.DataFrame:
    return pd.DataFrame({"image": image, "point_id": ids, "u": pixels[:, 0], "v": pixels[:, 1]})


#: Three cameras like the issue's: two 1920 x 1080 and one 1280 x 720, OpenCV's model, ~8-12 cm apart
#: and turned by a few degrees, so that a board 0.5-1 m away is seen whole by two or three of them.
RIG_CAMERAS = {
    "C0": Camera(1405.0, 1402.0, 963.0, 536.0, -0.365, 1920, 1080, "opencv", k2=0.145, p1=0.0008, p2=-0.0004,
                 k3=-0.029),
    "C1": Camera(1520.0, 1517.5, 951.0, 545.0, -0.30, 1920, 1080, "opencv", k2=0.11, p1=-0.0005, p2=0.0003,
                 k3=-0.02),
    "C2": Camera(905.0, 903.0, 644.0, 357.0, -0.25, 1280, 720, "opencv", k2=0.08, p1=0.0004, p2=0.0006, k3=-0.01),
}
RIG_CAM_FROM_RIG = {
    "C0": Rigid3.identity(),
    "C1": Rigid3(Rotation.from_euler("xyz", [0.5, -4.0, 0.8], degrees=True).as_matrix(), np.array([-0.10, 0.004, 0.002])),
    "C2": Rigid3(Rotation.from_euler("xyz", [-1.0, 3.0, -0.5], degrees=True).as_matrix(), np.array([0.08, -0.006, 0.01])),
}
