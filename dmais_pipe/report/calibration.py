"""Figures of the intrinsic calibration: residual vectors over each sensor and the RMS per image.

The residuals are the intrinsics stage's intrinsics/<camera>.residuals.csv (observed minus
projected, px) of the calibration images (after the final LM) and of the held-out images (after
their pose-only fit); the per-image RMS are those of intrinsics/<camera>.json.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
from matplotlib.figure import Figure

SPLIT_COLOURS = {"calib": "tab:blue", "eval": "tab:orange"}


def residual_quiver_figure(residuals: dict[str, pd.DataFrame], sizes: dict[str, tuple[int, int]]):
    """One panel per camera: an arrow per observation from its observed position along its residual,
    magnified so that the largest residual of all cameras spans ~8% of the sensor width (scale bar in
    the title). residuals: camera -> table (u, v, du, dv, split); sizes: camera -> (width, height)."""
    cameras = list(residuals)
    fig = Figure(figsize=(3.1 * len(cameras) + 0.4, 3.1))
    axes = fig.subplots(1, len(cameras), squeeze=False)[0]
    longest = max(float(np.nanmax(np.hypot(t["du"], t["dv"]))) if len(t) else 0.0 for t in residuals.values())
    widest = max(width for width, _ in sizes.values())
    gain = 0.08 * widest / longest if longest > 0 else 1.0
    for ax, camera in zip(axes, cameras):
        table, (width, height) = residuals[camera], sizes[camera]
        for split, colour in SPLIT_COLOURS.items():
            rows = table[table["split"] == split]
            ax.quiver(rows["u"], rows["v"], gain * rows["du"], gain * rows["dv"], color=colour, angles="xy",
                      scale_units="xy", scale=1.0, width=0.006, label=split, rasterized=True)
        ax.set_xlim(-0.5, width - 0.5)
        ax.set_ylim(height - 0.5, -0.5)
        ax.set_aspect("equal")
        ax.set_title(camera, fontsize=10)
        ax.set_xlabel("u (px)", fontsize=8)
        ax.tick_params(labelsize=7)
    axes[0].set_ylabel("v (px)", fontsize=8)
    axes[0].legend(fontsize=7, loc="lower left")
    fig.suptitle(f"residuals magnified {gain:.0f}x (arrow of 1 px = {gain:.0f} px)", fontsize=9)
    fig.tight_layout()
    return fig


def image_eps_table(records: list[dict]) -> pd.DataFrame:
    """One row per image of every camera record: camera, image, split, eps_px (RMS reprojection)."""
    rows = []
    for record in records:
        for split, key in (("calib", "image_eps_calib_px"), ("eval", "image_eps_eval_px")):
            for image, eps in (record.get(key) or {}).items():
                rows.append({"camera": record.get("camera", "?"), "image": image, "split": split, "eps_px": eps})
    return pd.DataFrame(rows, columns=["camera", "image", "split", "eps_px"])


def image_eps_figure(table: pd.DataFrame):
    """Bars of eps per image, grouped by camera, calibration and held-out images coloured apart."""
    fig = Figure(figsize=(max(6.0, 0.16 * len(table) + 2.0), 3.2))
    ax = fig.subplots()
    x, ticks, labels = 0, [], []
    for camera, rows in table.groupby("camera", sort=False):
        start = x
        for split, colour in SPLIT_COLOURS.items():
            mine = rows[rows["split"] == split]
            ax.bar(np.arange(x, x + len(mine)), mine["eps_px"], color=colour, width=0.8,
                   label=split if camera == table["camera"].iloc[0] else None)
            x += len(mine)
        ticks.append((start + x - 1) / 2)
        labels.append(camera)
        x += 1  # gap between cameras
    ax.set_xticks(ticks, labels)
    ax.set_ylabel("RMS reprojection (px)")
    ax.legend(fontsize=7)
    fig.tight_layout()
    return fig
