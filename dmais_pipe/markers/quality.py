"""Quality of the extracted markers per image and per camera (tables the evaluate stage writes).

Every corner carries the refinement's standard deviation sigma_px (per axis) and its fit residual
(markers/<image>.csv). An image is flagged when its median sigma_px is both above
FLAG_MIN_SIGMA_PX and FLAG_FACTOR times its camera's median over images: its corners are poor
against the same camera's others (blur, shadow, low contrast, a marker too small in the image).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

FLAG_FACTOR = 3.0
FLAG_MIN_SIGMA_PX = 0.05


def image_quality(markers: dict[str, pd.DataFrame], camera_of: dict[str, str], factor: float = FLAG_FACTOR,
                  min_sigma_px: float = FLAG_MIN_SIGMA_PX) -> pd.DataFrame:
    """One row per image: camera, image, detected, identified, median and 95th-percentile sigma_px,
    median fit_residual, flagged (median sigma above min_sigma_px and factor x its camera's median).
    markers: image -> its markers table (Workspace.load_markers)."""
    rows = []
    for image, table in markers.items():
        sigma = table["sigma_px"].to_numpy(float)
        rows.append({"camera": camera_of[image], "image": image, "detected": len(table),
                     "identified": int((table["point_id"] != "").sum()),
                     "sigma_median_px": _quantile(sigma, 0.5), "sigma_p95_px": _quantile(sigma, 0.95),
                     "fit_residual_median": _quantile(table["fit_residual"].to_numpy(float), 0.5)})
    frame = pd.DataFrame(rows, columns=["camera", "image", "detected", "identified", "sigma_median_px",
                                        "sigma_p95_px", "fit_residual_median"])
    camera_median = frame.groupby("camera")["sigma_median_px"].transform("median")
    frame["flagged"] = (frame["sigma_median_px"] > factor * camera_median) & (frame["sigma_median_px"] > min_sigma_px)
    return frame


def camera_quality(images: pd.DataFrame, markers: dict[str, pd.DataFrame], camera_of: dict[str, str]
                   ) -> pd.DataFrame:
    """One row per camera: images, detections, identified, the median / 95th percentile of every
    corner's sigma_px, and the flagged images (from `image_quality`)."""
    rows = []
    for camera, group in images.groupby("camera", sort=True):
        sigma = np.concatenate([markers[i]["sigma_px"].to_numpy(float) for i in group["image"]] or [np.zeros(0)])
        rows.append({"camera": camera, "images": len(group), "detected": int(group["detected"].sum()),
                     "identified": int(group["identified"].sum()), "sigma_median_px": _quantile(sigma, 0.5),
                     "sigma_p95_px": _quantile(sigma, 0.95),
                     "flagged_images": ", ".join(group.loc[group["flagged"], "image"]) or "none"})
    return pd.DataFrame(rows)


def _quantile(values: np.ndarray, q: float) -> float:
    values = values[np.isfinite(values)]
    return float(np.quantile(values, q)) if len(values) else float("nan")
