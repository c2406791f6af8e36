"""Images with their detected markers drawn over them (the paper's fig:calib and fig:A), one row per camera.

Each row: the whole image downsampled, every detection marked (identified: green circle and point
id; unidentified: red cross), then a few crops around single markers at full resolution. Pixel
coordinates follow the project's convention (centre of the top-left pixel at (0, 0)).
"""

from __future__ import annotations

import cv2
import numpy as np
import pandas as pd
from matplotlib.figure import Figure

OVERVIEW_WIDTH_PX = 480
CROP_DISPLAY_PX = 160
DEFAULT_CROP_PX = 400
CROP_LIMITS_PX = (64, 900)
IDENTIFIED, UNIDENTIFIED = "lime", "red"


def display_range(pixels: np.ndarray) -> tuple[float, float]:
    """(low, high): the 0.5 and 99.5 percentiles of an image's values (on every 8th pixel), high > low."""
    low, high = np.percentile(pixels[::8, ::8], (0.5, 99.5))
    return float(low), float(max(high, low + 1))


def stretched(pixels: np.ndarray, value_range: tuple[float, float]) -> np.ndarray:
    """(h, w) uint8 for display: `value_range` of an 8- or 16-bit image stretched to 0-255."""
    low, high = value_range
    return np.clip((pixels.astype(np.float32) - low) * (255.0 / (high - low)), 0, 255).astype(np.uint8)


def crop_size_px(markers: pd.DataFrame) -> int:
    """Side of a square crop showing one marker: 0.8 x the upper quartile of the distances to the
    nearest other detection (single markers are about their pitch apart, the corners of a board much
    closer), within CROP_LIMITS_PX; DEFAULT_CROP_PX for fewer than 2 detections."""
    uv = markers[["u", "v"]].to_numpy(float)
    if len(uv) < 2:
        return DEFAULT_CROP_PX
    distance = np.linalg.norm(uv[:, None] - uv[None], axis=2)
    np.fill_diagonal(distance, np.inf)
    return int(np.clip(0.8 * np.percentile(distance.min(axis=1), 75), *CROP_LIMITS_PX))


def pick_markers(markers: pd.DataFrame, count: int) -> pd.DataFrame:
    """Up to `count` detections spread across the image (by u): identified ones first, then one
    unidentified when there is any, so that both kinds are shown."""
    identified = markers[markers["point_id"] != ""].sort_values("u")
    unidentified = markers[markers["point_id"] == ""]
    room = count - (1 if len(unidentified) and count > 1 else 0)
    if len(identified) > room:
        identified = identified.iloc[np.linspace(0, len(identified) - 1, room).round().astype(int)]
    chosen = [identified] + ([unidentified.iloc[:count - len(identified)]] if len(unidentified) else [])
    return pd.concat(chosen).head(count)


def marker_montage(rows: list[tuple[str, np.ndarray, pd.DataFrame]], crops: int = 3):
    """Figure with one row per (label, pixels (h, w), markers u, v, point_id): overview + `crops` crops."""
    fig = Figure(figsize=(3.4 + 1.6 * crops, 2.3 * len(rows) + 0.3))
    widths = [2.2] + [1.0] * crops
    axes = fig.subplots(len(rows), crops + 1, squeeze=False, gridspec_kw={"width_ratios": widths})
    for row_axes, (label, pixels, markers) in zip(axes, rows):
        value_range = display_range(pixels)
        _overview(row_axes[0], pixels, value_range, markers, label)
        side = crop_size_px(markers)
        chosen = pick_markers(markers, crops)
        for ax, (_, marker) in zip(row_axes[1:], chosen.iterrows()):
            _crop(ax, pixels, value_range, marker, side)
        for ax in row_axes[1 + len(chosen):]:
            ax.axis("off")
    fig.tight_layout(pad=0.4)
    return fig


def _overview(ax, pixels: np.ndarray, value_range, markers: pd.DataFrame, label: str) -> None:
    height, width = pixels.shape
    scale = OVERVIEW_WIDTH_PX / width
    small = cv2.resize(pixels, (OVERVIEW_WIDTH_PX, max(1, round(height * scale))), interpolation=cv2.INTER_AREA)
    ax.imshow(stretched(small, value_range), cmap="gray", vmin=0, vmax=255, interpolation="nearest",
              extent=(-0.5, width - 0.5, height - 0.5, -0.5))
    known = markers["point_id"] != ""
    ax.scatter(markers.loc[known, "u"], markers.loc[known, "v"], s=40, facecolors="none",
               edgecolors=IDENTIFIED, linewidths=0.9)
    ax.scatter(markers.loc[~known, "u"], markers.loc[~known, "v"], s=30, marker="x", color=UNIDENTIFIED,
               linewidths=0.9)
    for _, marker in markers[known].iterrows():
        ax.annotate(marker["point_id"], (marker["u"], marker["v"]), xytext=(3, 3), textcoords="offset points",
                    fontsize=5, color=IDENTIFIED)
    ax.set_title(f"{label}: {int(known.sum())} identified, {int((~known).sum())} unidentified", fontsize=7)
    ax.set_xticks([])
    ax.set_yticks([])


def _crop(ax, pixels: np.ndarray, value_range, marker: pd.Series, side: int) -> None:
    """A `side` x `side` window centred on the marker, resampled to CROP_DISPLAY_PX, the detection marked."""
    height, width = pixels.shape
    u, v = float(marker["u"]), float(marker["v"])
    left = int(np.clip(round(u - side / 2), 0, max(width - side, 0)))
    top = int(np.clip(round(v - side / 2), 0, max(height - side, 0)))
    window = stretched(pixels[top:top + side, left:left + side], value_range)
    if window.shape[1] > CROP_DISPLAY_PX:
        window = cv2.resize(window, (CROP_DISPLAY_PX, CROP_DISPLAY_PX), interpolation=cv2.INTER_AREA)
    right, bottom = left + min(side, width), top + min(side, height)
    ax.imshow(window, cmap="gray", vmin=0, vmax=255, interpolation="nearest", extent=(left - 0.5, right - 0.5, bottom - 0.5, top - 0.5))
    identified = marker["point_id"] != ""
    ax.scatter([u], [v], s=60, marker="+", color=IDENTIFIED if identified else UNIDENTIFIED, linewidths=1.0)
    ax.set_title(marker["point_id"] if identified else "unidentified", fontsize=7)
    ax.set_xticks([])
    ax.set_yticks([])
