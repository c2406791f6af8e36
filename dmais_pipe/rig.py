"""A rig of cameras with known cam_from_rig, seen as one generalized camera.

For a pixel of camera c the generalized ray (paper, section Generalized Camera Model) is
alpha f + v in the rig frame, with v the camera centre in the rig frame and f the unit direction:
with rig_from_cam = (R_c, t_c), v = t_c and f = R_c K^-1 m~ (m~ the undistorted pixel).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .camera import Camera
from .errors import DmaisError
from .files import write_json_atomic
from .geometry import Rigid3


@dataclass
class Rig:
    """Cameras by name, their cam_from_rig transforms, and the reference camera (rig frame)."""

    cameras: dict[str, Camera]
    cam_from_rig: dict[str, Rigid3]
    reference_camera: str

    def __post_init__(self):
        if set(self.cameras) != set(self.cam_from_rig):
            raise DmaisError("rig: every camera needs exactly one cam_from_rig")
        self._check_known(self.reference_camera)

    @property
    def camera_names(self) -> list[str]:
        return list(self.cameras)

    @property
    def cameras_reference_first(self) -> list[str]:
        """The cameras, the reference first, the others in their order (COLMAP's camera ids 1, 2, ...)."""
        return [self.reference_camera] + [c for c in self.cameras if c != self.reference_camera]

    def camera_center(self, camera: str) -> np.ndarray:
        """(3,) centre of `camera` in the rig frame (the paper's v)."""
        self._check_known(camera)
        return self.cam_from_rig[camera].center

    def rays(self, camera: str, uv) -> tuple[np.ndarray, np.ndarray]:
        """Generalized rays of distorted pixels uv (n, 2) of one camera.

        Returns origins v (n, 3) and unit directions f (n, 3) in the rig frame.
        """
        self._check_known(camera)
        rig_from_cam = self.cam_from_rig[camera].inverse()
        directions = self.cameras[camera].unproject(uv) @ rig_from_cam.R.T
        origins = np.broadcast_to(rig_from_cam.t, directions.shape).copy()
        return origins, directions

    def rays_of(self, cameras, uv) -> tuple[np.ndarray, np.ndarray]:
        """Generalized rays of observations from mixed cameras: names (n,), pixels (n, 2). Each camera's rows
        are found by comparing the names with it (numpy's unique of n strings sorts them); a name not in
        the rig raises naming the first of them in sorted order."""
        cameras = np.asarray(cameras)
        uv = np.asarray(uv, dtype=float).reshape(-1, 2)
        if len(cameras) != len(uv):
            raise DmaisError(f"rig: {len(cameras)} camera names for {len(uv)} pixels")
        origins = np.empty((len(uv), 3))
        directions = np.empty((len(uv), 3))
        found = np.zeros(len(uv), dtype=bool)
        for name in self.cameras:
            mask = cameras == name
            found |= mask
            if mask.any():
                origins[mask], directions[mask] = self.rays(name, uv[mask])
        if not found.all():
            self._check_known(str(np.unique(cameras[~found])[0]))
        return origins, directions

    def project(self, camera: str, rig_from_world: Rigid3, points_world) -> np.ndarray:
        """Distorted pixels (n, 2) in `camera` of world points (n, 3) for a rig pose."""
        self._check_known(camera)
        cam_from_world = self.cam_from_rig[camera] * rig_from_world
        return self.cameras[camera].project(cam_from_world.apply(points_world))

    def project_rig_points(self, camera: str, points_rig) -> np.ndarray:
        """Distorted pixels (n, 2) in `camera` of points (n, 3) in the rig frame."""
        self._check_known(camera)
        return self.cameras[camera].project(self.cam_from_rig[camera].apply(points_rig))

    def to_dict(self) -> dict:
        """The rig.json layout of docs/design.md."""
        return {
            "reference_camera": self.reference_camera,
            "cameras": [
                {"name": name, **camera.to_dict(), "cam_from_rig": self.cam_from_rig[name].to_dict()}
                for name, camera in self.cameras.items()
            ],
        }

    @classmethod
    def from_dict(cls, data: dict) -> "Rig":
        cameras, cam_from_rig = {}, {}
        for entry in data["cameras"]:
            cameras[entry["name"]] = Camera.from_dict(entry)
            cam_from_rig[entry["name"]] = Rigid3.from_dict(entry["cam_from_rig"])
        return cls(cameras, cam_from_rig, data["reference_camera"])

    def save(self, path: str | Path, **extra) -> Path:
        """Write rig.json (atomically); `extra` keys are stored beside the rig."""
        return write_json_atomic(path, {**self.to_dict(), **extra})

    @classmethod
    def load(cls, path: str | Path) -> "Rig":
        path = Path(path)
        try:
            return cls.from_dict(json.loads(path.read_text()))
        except FileNotFoundError:
            raise DmaisError(f"{path}: rig file not found") from None
        except (KeyError, TypeError, ValueError, json.JSONDecodeError) as error:
            raise DmaisError(f"{path}: not a valid rig file ({error})") from None

    def _check_known(self, camera: str) -> None:
        if camera not in self.cameras:
            raise DmaisError(f"unknown camera {camera!r}; the rig has {', '.join(self.cameras)}")
