"""Camera-layout figure of calibrated rigs (paper fig:extrinsics): centres and viewing frustums, one colour per case.

Every rig is drawn in its own rig frame (the reference camera's), all cases on the same 3D axes so
that the calibrations with and without camera-centre priors can be compared. Each camera of each
case is one SVG group with the id `layout-<case>-<camera>` (case = 0-based index), so tools and tests
can find it.
"""

from __future__ import annotations

import io
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure
from matplotlib.lines import Line2D

from ..errors import DmaisError
from ..files import write_bytes_atomic
from ..rig import Rig
from .footprint import image_corner_rays

COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown")
MARKERS = ("o", "^", "s", "D", "v", "P")


def artist_id(case: int, camera: str) -> str:
    """SVG id of one camera's frustum in case `case`."""
    return f"layout-{case}-{camera}"


def frustum_segments(rig: Rig, camera: str, depth: float) -> np.ndarray:
    """(8, 2, 3) line segments of a camera's viewing pyramid in the rig frame, `depth` metres deep.

    Four edges from the centre to the image corners at depth `depth` along the optical axis, and
    the four sides of the far rectangle.
    """
    rays = image_corner_rays(rig.cameras[camera])
    rig_from_cam = rig.cam_from_rig[camera].inverse()
    far = (rays / rays[:, 2:] * depth) @ rig_from_cam.R.T + rig_from_cam.t
    centre = rig_from_cam.t
    edges = [(centre, p) for p in far] + [(far[k], far[(k + 1) % 4]) for k in range(4)]
    return np.array(edges)


def _extent(rigs: Sequence[Rig]) -> float:
    centres = np.array([rig.camera_center(c) for rig in rigs for c in rig.camera_names])
    return max(float(np.ptp(centres, axis=0).max()), 0.05)


def layout_figure(rigs: Sequence[Rig], labels: Sequence[str], title: str = "Camera layout (rig frame)") -> Figure:
    """Figure with one 3D axes: per case, camera centres (markers) and frustums (lines), a legend entry."""
    from mpl_toolkits.mplot3d.art3d import Line3DCollection

    if len(rigs) != len(labels) or not rigs:
        raise DmaisError(f"camera layout: {len(rigs)} rig(s) for {len(labels)} label(s)")
    extent = _extent(rigs)
    fig = Figure(figsize=(6.4, 6.0))
    ax = fig.add_subplot(projection="3d")
    handles = []
    for k, (rig, label) in enumerate(zip(rigs, labels)):
        colour, marker = COLOURS[k % len(COLOURS)], MARKERS[k % len(MARKERS)]
        for name in rig.camera_names:
            lines = Line3DCollection(frustum_segments(rig, name, 0.6 * extent), colors=colour, linewidths=0.8)
            lines.set_gid(artist_id(k, name))
            ax.add_collection3d(lines)
            ax.scatter(*rig.camera_center(name), color=colour, marker=marker, s=18)
            if k == 0:
                ax.text(*rig.camera_center(name), f"  {name}", fontsize=8)
        handles.append(Line2D([], [], color=colour, marker=marker, label=label))
    _frame_axes(ax, rigs, extent)
    ax.legend(handles=handles, loc="upper left", fontsize=8)
    ax.set_title(title, fontsize=10)
    return fig


def _frame_axes(ax, rigs: Sequence[Rig], extent: float) -> None:
    """Equal-aspect limits around all centres, z pointing down (the cameras look down)."""
    centres = np.array([rig.camera_center(c) for rig in rigs for c in rig.camera_names])
    middle, half = (centres.max(axis=0) + centres.min(axis=0)) / 2, 0.8 * extent
    ax.set(xlim=(middle[0] - half, middle[0] + half), ylim=(middle[1] - half, middle[1] + half),
           zlim=(middle[2] + 1.2 * half, middle[2] - 0.4 * half))
    ax.set_box_aspect((1, 1, 1))
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")


def write_layout_svg(path: str | Path, rigs: Sequence[Rig], labels: Sequence[str], **kwargs) -> Path:
    """Draw `layout_figure(rigs, labels)` and write it to `path` as SVG (atomically)."""
    import matplotlib

    fig = layout_figure(rigs, labels, **kwargs)
    buffer = io.BytesIO()
    with matplotlib.rc_context({"svg.fonttype": "none", "svg.hashsalt": "dmais-layout"}):
        fig.savefig(buffer, format="svg", bbox_inches="tight")
    return write_bytes_atomic(path, buffer.getvalue())
