"""Benchmark of marker extraction on a rendered dataset with ground truth (`truth/observations.csv`).

Per image: detection time, recall of the true X-corners, false positives, identification
(correct / wrong / unidentified, judged by the distance of a detection to the true projection
carrying its id) and sub-pixel RMS of `refine` beside `cv2.cornerSubPix` (win 11) from the same
starting points (truth + 0.3...1.5 px). The truth lists only points >= 20 px inside the image:
unmatched detections nearer the border are counted as `border`, not as false positives.
"""

from __future__ import annotations

import logging
import resource
import time

import cv2
import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from ..dataset import Dataset
from ..files import write_csv_atomic
from ..rig import Rig
from ..markers.detect import detect
from ..markers.identify import identify
from ..markers.refine import refine
from ..markers.extract import predicted_projections

log = logging.getLogger(__name__)
MATCH_PX = 2.0
BORDER_PX = 25.0


def _corner_sub_pix(image, start) -> np.ndarray:
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_COUNT, 100, 1e-4)
    points = np.asarray(start, dtype=np.float32).reshape(-1, 1, 2).copy()
    return cv2.cornerSubPix(image, points, (11, 11), (-1, -1), criteria).reshape(-1, 2).astype(float)


def bench_markers(dataset_dir, out_csv=None, rig_path=None, images=None, seed: int = 0) -> pd.DataFrame:
    """One row per image with a file (or per `images`); also written to `out_csv` if given.

    rig_path: a rig.json used to predict flight images (e.g. RESULTS/rig.json); without it flight
    detections are not identified.
    """
    dataset = Dataset.load(dataset_dir)
    truth = pd.read_csv(dataset.truth_dir / "observations.csv", dtype={"image": str, "point_id": str})
    rig = Rig.load(rig_path) if rig_path else None
    rng = np.random.default_rng(seed)
    names = images or [i for i, p in zip(dataset.images["image"], dataset.images["path"]) if p]
    rows = []
    for k, image in enumerate(names, 1):
        pixels = dataset.read_image(image)
        height, width = pixels.shape
        true = truth[truth["image"] == image]
        true_uv = true[["u", "v"]].to_numpy(dtype=float)
        started = time.perf_counter()
        found, rejected = detect(pixels, with_rejected=True)
        seconds = time.perf_counter() - started
        uv = found[["u", "v"]].to_numpy()
        prediction = predicted_projections(dataset, image, rig)
        ids = np.full(len(uv), "", dtype=object)
        if prediction is not None and len(uv):
            ids = identify(uv, prediction[0], prediction[1], (width, height),
                           rejected=rejected[["u", "v"]].to_numpy(dtype=float))
        hit = np.zeros(len(true_uv), dtype=bool)
        matched = np.zeros(len(uv), dtype=bool)
        correct = wrong = 0
        if len(true_uv) and len(uv):
            distance, index = cKDTree(uv).query(true_uv)
            hit = distance < MATCH_PX
            matched[index[hit]] = True
            true_id = dict(zip(index[hit], true["point_id"].to_numpy()[hit]))
            for d, given in enumerate(ids):
                if given and d in true_id:
                    correct += given == true_id[d]
                    wrong += given != true_id[d]
        near_border = ((uv[:, 0] < BORDER_PX) | (uv[:, 1] < BORDER_PX) | (uv[:, 0] > width - 1 - BORDER_PX)
                       | (uv[:, 1] > height - 1 - BORDER_PX)) if len(uv) else np.zeros(0, bool)
        angle = rng.uniform(0, 2 * np.pi, len(true_uv))
        start = true_uv + rng.uniform(0.3, 1.5, len(true_uv))[:, None] * np.column_stack([np.cos(angle), np.sin(angle)])
        ours = refine(pixels, start) - true_uv if len(true_uv) else np.zeros((0, 2))
        theirs = (_corner_sub_pix(pixels, start) - true_uv) if len(true_uv) and pixels.dtype == np.uint8 else np.zeros((0, 2))
        rows.append({
            "image": image, "n_true": len(true_uv), "n_detected": len(uv), "recall": hit.mean() if len(hit) else 1.0,
            "false_positives": int(np.count_nonzero(~matched & ~near_border)),
            "border": int(np.count_nonzero(~matched & near_border)),
            "identified": int(np.count_nonzero(ids != "")), "correct_ids": int(correct), "wrong_ids": int(wrong),
            "detect_s": seconds,
            "detect_rms_px": float(np.sqrt(np.mean(np.sum((uv[index[hit]] - true_uv[hit]) ** 2, 1)))) if hit.any() else np.nan,
            "refine_sq_sum": float(np.nansum(ours**2)), "refine_failed": int(np.isnan(ours).any(1).sum()),
            "cornersubpix_sq_sum": float(np.sum(theirs**2)),
            "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0,
        })
        log.info("bench markers %d/%d %s: %d/%d found, %.2f s", k, len(names), image, int(hit.sum()), len(true_uv), seconds)
    frame = pd.DataFrame(rows)
    if out_csv is not None:
        write_csv_atomic(out_csv, frame)
    return frame


def summary(frame: pd.DataFrame) -> dict:
    """Totals over a bench_markers frame."""
    n = frame["n_true"].sum()
    return {
        "images": len(frame), "true_points": int(n), "recall": float((frame["recall"] * frame["n_true"]).sum() / max(n, 1)),
        "false_positives": int(frame["false_positives"].sum()), "border_detections": int(frame["border"].sum()),
        "identified": int(frame["identified"].sum()), "wrong_ids": int(frame["wrong_ids"].sum()),
        "refine_rms_px": float(np.sqrt(frame["refine_sq_sum"].sum() / max(n, 1))),
        "cornersubpix_rms_px": float(np.sqrt(frame["cornersubpix_sq_sum"].sum() / max(n, 1))),
        "refine_failed": int(frame["refine_failed"].sum()),
        "detect_s_mean": float(frame["detect_s"].mean()), "detect_s_max": float(frame["detect_s"].max()),
        "peak_rss_mb": float(frame["peak_rss_mb"].max()),
    }
