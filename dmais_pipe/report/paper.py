"""Our tables beside the paper's published numbers, with their ratio.

The published numbers are transcribed once from the paper's LaTeX into `dmais_pipe/report/paper_tables/*.csv` (package data)
with the column names of our RESULTS/tables/*.csv; a column the paper does not report is absent.
Conventions of the transcription:

- intrinsics.csv (tab:intrinsics): method in lower case (bouguet, opencv, babelcalib, ours);
  our `dlt_lm` baseline (Bouguet/Tsai-style DLT + LM) is compared with the paper's `bouguet` row.
- extrinsics_R.csv / extrinsics_t.csv: the paper's tuples are (z, y, x) ZYX Euler angles of
  rig_from_cam in degrees and (x, y, z) camera centres in metres.
- pose_methods.csv, conf.csv: groups 1..5 are the paper's circled numbers; subset labels are the
  camera indexes (0, 01, 012, 1234, 01234), kept as text. The paper's tab:conf prints 5.418 px for
  group 5 with all cameras where tab:pose_methods prints 5.148; both are transcribed as printed.
- time_points.csv: the paper's times as `paper_ms`, compared with our `ours_ms`.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from ..errors import DmaisError

log = logging.getLogger(__name__)

PAPER_DIR = Path(__file__).resolve().parent / "paper_tables"
COMPARISON_COLUMNS = ("quantity", "ours", "paper", "ratio", "difference")


@dataclass(frozen=True)
class PaperTable:
    """How one of our tables meets its published counterpart.

    keys: columns identifying a row; columns: our column -> published column to compare (None:
    every numeric column both have); aliases: key column -> {our value: the paper's value}.
    """

    keys: tuple[str, ...]
    columns: Mapping[str, str] | None = None
    aliases: Mapping[str, Mapping[str, str]] = field(default_factory=dict)


PAPER_TABLES = {
    "intrinsics": PaperTable(("method", "camera"), aliases={"method": {"dlt_lm": "bouguet"}}),
    "extrinsics_R": PaperTable(("camera",)),
    "extrinsics_t": PaperTable(("camera",)),
    "pose_methods": PaperTable(("group",)),
    "conf": PaperTable(("group", "subset")),
    "time_points": PaperTable(("n_points",), columns={"ours_ms": "paper_ms"}),
}


def compare_with_paper(ours: pd.DataFrame, published: pd.DataFrame, keys: Sequence[str],
                       columns: Mapping[str, str] | None = None) -> pd.DataFrame:
    """Long table: keys..., quantity, ours, paper, ratio (ours / paper), difference (ours - paper).

    ours: (n, k) our table; published: (m, k') the paper's; keys: columns present in both, matched
    as text (integral numbers without decimals). columns: our column -> published column; default
    every numeric column of `ours` that `published` also has. Rows of either side without a match
    keep NaN on the other side; quantities the paper leaves empty everywhere are dropped.
    One output row per matched (row, quantity), ours' row order first.
    """
    keys = list(keys)
    columns = dict(columns) if columns is not None else _shared_numeric(ours, published, keys)
    left = _keyed(ours, keys, list(columns))
    right = _keyed(published, keys, list(columns.values())).rename(
        columns={paper: f"{mine}__paper" for mine, paper in columns.items()})
    merged = left.merge(right, on=keys, how="outer", sort=False)
    rows = []
    for mine in columns:
        paper = merged[f"{mine}__paper"]
        if paper.isna().all():
            continue
        part = merged[keys].assign(quantity=mine, ours=merged[mine], paper=paper)
        rows.append(part)
    if not rows:
        return pd.DataFrame(columns=keys + list(COMPARISON_COLUMNS))
    out = pd.concat(rows, ignore_index=True)
    order = _row_order(left, right, keys)
    out["_row"] = [order[tuple(k)] for k in out[keys].itertuples(index=False, name=None)]
    out = out.sort_values("_row", kind="stable").drop(columns="_row").reset_index(drop=True)
    with np.errstate(divide="ignore", invalid="ignore"):
        out["ratio"] = np.where(out["paper"] != 0, out["ours"] / out["paper"], np.nan)
    out["difference"] = out["ours"] - out["paper"]
    return out


def _row_order(left: pd.DataFrame, right: pd.DataFrame, keys: list[str]) -> dict[tuple, int]:
    """Key tuple -> position: ours' rows in their order, then the paper's rows we lack."""
    order: dict[tuple, int] = {}
    for frame in (left, right):
        for key in frame[keys].itertuples(index=False, name=None):
            order.setdefault(tuple(key), len(order))
    return order


def _shared_numeric(ours: pd.DataFrame, published: pd.DataFrame, keys: list[str]) -> dict[str, str]:
    return {c: c for c in ours.columns
            if c not in keys and c in published.columns and pd.api.types.is_numeric_dtype(ours[c])}


def _keyed(frame: pd.DataFrame, keys: list[str], values: list[str]) -> pd.DataFrame:
    """keys as text + the value columns as floats (missing value columns become NaN)."""
    out = pd.DataFrame({k: _key_text(frame[k]) for k in keys})
    for column in values:
        out[column] = pd.to_numeric(frame[column], errors="coerce") if column in frame else np.nan
    return out


def _key_text(values: pd.Series) -> pd.Series:
    if pd.api.types.is_numeric_dtype(values) and np.all(np.mod(values.dropna(), 1) == 0):
        return values.map(lambda v: "" if pd.isna(v) else str(int(v))).astype(object)
    return values.astype(str).str.strip().astype(object)


# ------------------------------------------------------------------------------ files


def read_table(path: str | Path, keys: Sequence[str]) -> pd.DataFrame:
    """A table CSV with its key columns read as text (so that subset '012' stays '012')."""
    return pd.read_csv(path, dtype={k: str for k in keys})


def paper_comparisons(ours: Mapping[str, pd.DataFrame], paper_dir: str | Path | None = None
                      ) -> dict[str, pd.DataFrame]:
    """name -> compare_with_paper(...) for every table of PAPER_TABLES present on both sides.

    ours: name -> our table (its key columns as text); the paper's are `paper_dir`/<name>.csv
    (default: the package's paper_tables).
    """
    paper_dir = Path(paper_dir) if paper_dir is not None else PAPER_DIR
    out = {}
    for name, spec in PAPER_TABLES.items():
        paper_path = paper_dir / f"{name}.csv"
        if name not in ours or not paper_path.is_file():
            log.info("paper comparison %s skipped: %s missing", name, "our table" if name not in ours else paper_path)
            continue
        table = _aliased(ours[name], spec.aliases)
        out[name] = compare_with_paper(table, read_table(paper_path, spec.keys), spec.keys, spec.columns)
    return out


def paper_notes(paper_dir: str | Path | None = None) -> dict[str, str]:
    """table name -> why ours differs from the published table (`paper_dir`/notes.yaml; {} without)."""
    path = (Path(paper_dir) if paper_dir is not None else PAPER_DIR) / "notes.yaml"
    if not path.is_file():
        return {}
    notes = yaml.safe_load(path.read_text()) or {}
    unknown = sorted(set(notes) - set(PAPER_TABLES))
    if unknown:
        raise DmaisError(f"{path}: notes for unknown table(s) {unknown}; tables are {sorted(PAPER_TABLES)}")
    return {name: str(text) for name, text in notes.items()}


def _aliased(frame: pd.DataFrame, aliases: Mapping[str, Mapping[str, str]]) -> pd.DataFrame:
    frame = frame.copy()
    for column, mapping in aliases.items():
        if column in frame:
            frame[column] = frame[column].map(lambda v: mapping.get(v, v))
    return frame
