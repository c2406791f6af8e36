"""`dmais bench markers --suite regimes|effects|photos|texture|all`: print the tables and write their CSVs.

CSV paths: beside `csv` (e.g. reports/bench/markers.csv), markers_regimes.csv, markers_effects.csv,
markers_photos.csv and markers_texture.csv.
"""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from ..files import write_csv_atomic
from .marker_effects import bench_effects
from .marker_photos import bench_photos
from .marker_regimes import bench_regimes
from .marker_texture import bench_texture


def _print(title: str, frame: pd.DataFrame, path: Path) -> None:
    write_csv_atomic(path, frame)
    print(f"== {title}")
    with pd.option_context("display.width", 250, "display.max_rows", 1000, "display.max_colwidth", 60):
        print(frame.to_string(index=False, float_format=lambda x: f"{x:.4f}"))
    print(f"CSV: {path}\n")


def run_suite(suite: str, csv, seed: int = 0, images: int | None = None) -> dict[str, pd.DataFrame]:
    """Run one suite ('regimes', 'effects', 'photos', 'texture') or 'all'; returns the tables by suite name."""
    base = Path(csv)
    out = {}
    if suite in ("regimes", "all"):
        frame = bench_regimes(images=images or 4, seed=seed)
        shown = frame.drop(columns=[c for c in frame.columns if c.startswith("csp") and c[3].isdigit()])
        _print("refinement per regime: ours vs cv2.cornerSubPix (best window of the cell) from the same starts",
               shown, base.with_name(base.stem + "_regimes.csv"))
        print(f"cells meeting the target: {int(frame['ok'].sum())} / {len(frame)}; rejected {int(frame['rejected'].sum())}"
              f" of {int(frame['n'].sum())} corners\n")
        out["regimes"] = frame
    if suite in ("effects", "all"):
        out["effects"] = bench_effects(images=images or 10, seed=seed)
        _print("detection and refinement per aerial effect", out["effects"], base.with_name(base.stem + "_effects.csv"))
    if suite in ("photos", "all"):
        out["photos"] = bench_photos()
        _print("real chessboard photographs: residual to a camera model fitted to each refiner's corners",
               out["photos"], base.with_name(base.stem + "_photos.csv"))
    if suite in ("texture", "all"):
        out["texture"] = bench_texture(images=images or 2, seed=seed)
        _print("detection on textured ground (12 MP, 10 markers each: nominal 30-500 px, faint 30-120 px of 75-170 DN "
               "up to 60 deg; last row: all cells)",
               out["texture"], base.with_name(base.stem + "_texture.csv"))
        print(f"cells meeting the target: {int(out['texture']['ok'].iloc[:-1].sum())} / {len(out['texture']) - 1}\n")
    return out
