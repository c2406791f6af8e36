"""Detection on textured ground (grass or gravel in sun): false detections, recall, sub-pixel error.

Every cell of the grid (kind of markers `MARKERS` x texture standard deviation `STDS_DN` x texture
blur `BLURS_PX`) renders `images` seeded 12 MP scenes (`marker_scenes.textured_scene`: ten markers,
optical blur 0.8 px, read noise 2 DN, on ground of mean 110 DN whose texture the image shows as
white noise blurred by the cell's blur with the cell's standard deviation) and runs `detect` on
each. The kinds: 'nominal', 30-500 px foreshortened up to 45 deg, levels 35 / 205 DN +- 10 %;
'faint', 30-120 px up to 60 deg (a 30 px one then ~15 px across), contrast 75-170 DN (a marker in
the shade). A detection within MATCH_PX of a true corner is true, any other is false. Per cell:
recall, false detections per image (mean and worst image), RMS and worst error of the true
detections, the score and sigma_px ranges of the true and the false ones, and the mean detection
time. `ok`: recall at least MIN_RECALL and at most MAX_FALSE_PER_IMAGE false detections per image
on average.
"""

from __future__ import annotations

import itertools
import time

import numpy as np
import pandas as pd
from scipy.spatial import cKDTree

from ..markers.detect import detect
from .marker_scenes import textured_scene

STDS_DN = (15.0, 25.0, 40.0)
BLURS_PX = (0.8, 1.2, 2.0)
#: textured_scene's options of each kind of markers
MARKERS = {"nominal": {},
           "faint": {"sizes_px": (30.0, 120.0), "max_tilt_deg": 60.0, "contrasts_dn": (75.0, 170.0)}}
MATCH_PX = 1.0
MIN_RECALL = 0.99
MAX_FALSE_PER_IMAGE = 1


def cell_seed(seed: int, index: int) -> int:
    """The seed of the index-th cell of a table of `seed`."""
    return seed * 7919 + index


def texture_scenes(texture_dn: float, texture_blur_px: float, images: int, seed: int, **scene):
    """`images` scenes (image (h, w) uint8, truth (n, 2)) of one cell, drawn from one generator;
    `scene`: further arguments of `textured_scene` (e.g. a smaller camera and slots)."""
    rng = np.random.default_rng(seed)
    for _ in range(images):
        yield textured_scene(rng, texture_dn, texture_blur_px, **scene)


def match(found: pd.DataFrame, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """For detections `found` (k rows) of an image whose true corners are truth (n, 2): (true (k,),
    within MATCH_PX of a true corner; error (k,) px to the nearest true corner; hit (n,), a true
    corner with a detection within MATCH_PX)."""
    uv = found[["u", "v"]].to_numpy()
    if len(uv) == 0:
        return np.zeros(0, dtype=bool), np.zeros(0), np.zeros(len(truth), dtype=bool)
    error = cKDTree(truth).query(uv)[0]
    return error < MATCH_PX, error, cKDTree(uv).query(truth)[0] < MATCH_PX


def measure_cell(texture_dn: float, texture_blur_px: float, images: int, seed: int, **scene) -> dict:
    """One row of the texture table (without its kind of markers)."""
    n_true = found = 0
    false, errors, seconds, true_rows, false_rows = [], [], [], [], []
    for image, truth in texture_scenes(texture_dn, texture_blur_px, images, seed, **scene):
        started = time.perf_counter()
        detections = detect(image)
        seconds.append(time.perf_counter() - started)
        true, error, hit = match(detections, truth)
        n_true += len(truth)
        found += int(hit.sum())
        false.append(int(np.count_nonzero(~true)))
        errors.append(error[true])
        true_rows.append(detections[true])
        false_rows.append(detections[~true])
    errors = np.concatenate(errors)
    true_rows, false_rows = pd.concat(true_rows), pd.concat(false_rows)
    return {"texture_dn": texture_dn, "texture_blur_px": texture_blur_px, "images": images, "n_true": n_true,
            "found": found, "recall": found / max(n_true, 1), "false_per_image": float(np.mean(false)),
            "false_max": max(false), "rms_px": float(np.sqrt(np.mean(errors**2))) if len(errors) else np.nan,
            "max_px": float(errors.max()) if len(errors) else np.nan,
            **_ranges("true", true_rows), **_ranges("false", false_rows), "detect_s": float(np.mean(seconds))}


def _ranges(kind: str, rows: pd.DataFrame) -> dict:
    """The score and sigma_px ranges of detections `rows` as columns named after `kind`."""
    out = {}
    for column, name in (("score", "score"), ("sigma_px", "sigma")):
        values = rows[column].to_numpy()
        out[f"{kind}_{name}_min"] = float(values.min()) if len(values) else np.nan
        out[f"{kind}_{name}_max"] = float(values.max()) if len(values) else np.nan
    return out


def bench_texture(images: int = 2, seed: int = 0, stds=STDS_DN, blurs=BLURS_PX, markers=tuple(MARKERS)
                  ) -> pd.DataFrame:
    """One row per (kind of markers, texture std, texture blur) cell and an 'all' row (markers
    'all', texture_dn NaN) of their totals; `ok`: recall at least MIN_RECALL and at most
    MAX_FALSE_PER_IMAGE false detections per image on average. The nominal cells' seeds are those
    of a table without kinds."""
    rows = []
    for kind_index, kind in enumerate(markers):
        cells = itertools.product(stds, blurs)
        offset = kind_index * len(stds) * len(blurs)
        rows += [{"markers": kind, **measure_cell(std, blur, images, cell_seed(seed, offset + k), **MARKERS[kind])}
                 for k, (std, blur) in enumerate(cells)]
    frame = pd.DataFrame(rows)
    frame = pd.concat([frame, pd.DataFrame([{"markers": "all", **_total(frame)}])], ignore_index=True)
    frame["ok"] = (frame["recall"] >= MIN_RECALL) & (frame["false_per_image"] <= MAX_FALSE_PER_IMAGE)
    return frame


def _total(frame: pd.DataFrame) -> dict:
    """The 'all' row of the cells' rows `frame`."""
    found, images = frame["found"].sum(), frame["images"].sum()
    total = {"texture_dn": np.nan, "texture_blur_px": np.nan, "images": int(images),
             "n_true": int(frame["n_true"].sum()), "found": int(found), "recall": float(found / frame["n_true"].sum()),
             "false_per_image": float((frame["false_per_image"] * frame["images"]).sum() / images),
             "false_max": int(frame["false_max"].max()),
             "rms_px": float(np.sqrt((frame["rms_px"] ** 2 * frame["found"]).sum() / max(found, 1))),
             "max_px": float(frame["max_px"].max())}
    for kind, name in itertools.product(("true", "false"), ("score", "sigma")):
        total[f"{kind}_{name}_min"] = frame[f"{kind}_{name}_min"].min()
        total[f"{kind}_{name}_max"] = frame[f"{kind}_{name}_max"].max()
    total["detect_s"] = float((frame["detect_s"] * frame["images"]).sum() / images)
    return total
