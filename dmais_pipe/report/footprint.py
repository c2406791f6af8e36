"""The cameras' fields of view merged on the ground (the paper's fig:5cam) and the rig's total angular extent.

Each camera's four image corners are unprojected (with its distortion) to rays, carried to the
world by one frame's rig_from_world and cut with the horizontal plane z = ground_z. The angular
extent is measured in the reference camera's frame (the rig frame): the spread of the azimuths
atan2(x, z) and elevations atan2(y, z) of every camera's corner rays, i.e. the field of view a
single camera looking along the reference axis would need to see all of them.
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Polygon

from ..camera import Camera
from ..geometry import Rigid3
from ..rig import Rig


def image_corner_rays(cam: Camera) -> np.ndarray:
    """(4, 3) rays (z > 0, not of one length) through the outer corners of the image of `cam`, in its own frame
    (clockwise from top-left); the pinhole corners where the distortion cannot be inverted there."""
    corners = np.array([[-0.5, -0.5], [cam.width - 0.5, -0.5], [cam.width - 0.5, cam.height - 0.5],
                        [-0.5, cam.height - 0.5]])
    rays = cam.unproject(corners)
    if not np.all(np.isfinite(rays)):
        rays = np.column_stack([(corners - [cam.cx, cam.cy]) / [cam.fx, cam.fy], np.ones(4)])
    return rays


def corner_rays(rig: Rig, camera: str) -> np.ndarray:
    """(4, 3) unit rays through the outer corners of `camera`'s image, in the rig frame (clockwise from top-left)."""
    rays = image_corner_rays(rig.cameras[camera]) @ rig.cam_from_rig[camera].R  # rig_from_cam = cam_from_rig.R^T
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def angular_extent_deg(rig: Rig) -> tuple[float, float]:
    """(horizontal, vertical) angles in degrees spanned by all cameras' corner rays, seen along the
    reference camera's optical axis (rig frame x, y, z = right, down, forward)."""
    rays = np.vstack([corner_rays(rig, c) for c in rig.camera_names])
    azimuth = np.degrees(np.arctan2(rays[:, 0], rays[:, 2]))
    elevation = np.degrees(np.arctan2(rays[:, 1], rays[:, 2]))
    return float(np.ptp(azimuth)), float(np.ptp(elevation))


def ground_footprints(rig: Rig, rig_from_world: Rigid3, ground_z: float) -> dict[str, np.ndarray | None]:
    """camera -> (4, 2) world x, y where its corner rays meet the plane z = ground_z; None for a camera
    with a corner ray that does not reach the plane (looking above the horizon)."""
    world_from_rig = rig_from_world.inverse()
    out = {}
    for camera in rig.camera_names:
        rays = corner_rays(rig, camera) @ world_from_rig.R.T
        centre = world_from_rig.apply(rig.camera_center(camera)[None])[0]
        with np.errstate(divide="ignore", invalid="ignore"):
            depth = (ground_z - centre[2]) / rays[:, 2]
        out[camera] = centre[:2] + depth[:, None] * rays[:, :2] if np.all(depth > 0) else None
    return out


def footprint_figure(footprints: dict[str, np.ndarray | None], rig_centre_xy: np.ndarray,
                     ground_points_xy: np.ndarray | None = None, title: str = ""):
    """Top view of the footprints (one polygon per camera), the rig's ground point and the markers."""
    fig = Figure(figsize=(6.2, 6.0))
    ax = fig.subplots()
    if ground_points_xy is not None and len(ground_points_xy):
        ax.scatter(*ground_points_xy.T, s=4, color="0.6", label="ground markers", zorder=1)
    colours = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown", "tab:pink")
    drawn = []
    for k, (camera, corners) in enumerate(footprints.items()):
        if corners is None:
            continue
        colour = colours[k % len(colours)]
        ax.add_patch(Polygon(corners, closed=True, facecolor=colour, alpha=0.35, edgecolor=colour, lw=1.2,
                             label=camera, zorder=2))
        ax.annotate(camera, corners.mean(axis=0), ha="center", va="center", fontsize=9, zorder=3)
        drawn.append(corners)
    ax.scatter(*rig_centre_xy, marker="+", s=80, color="k", label="rig (nadir)", zorder=3)
    if drawn:
        everything = np.vstack(drawn + [rig_centre_xy[None]])
        low, high = everything.min(axis=0), everything.max(axis=0)
        pad = 0.08 * float(np.max(high - low))
        ax.set_xlim(low[0] - pad, high[0] + pad)
        ax.set_ylim(low[1] - pad, high[1] + pad)
    ax.set_aspect("equal")
    ax.set_xlabel("world x (m)")
    ax.set_ylabel("world y (m)")
    ax.legend(fontsize=7, loc="best")
    if title:
        ax.set_title(title, fontsize=10)
    fig.tight_layout()
    return fig
