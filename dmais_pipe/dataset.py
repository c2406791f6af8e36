"""Reading, validating and writing a dataset directory: the one place that parses inputs.

The format is documented for users in docs/dataset.md. Every CSV cell is read as a string, stripped
of surrounding blanks and converted here, so that a bad value is reported with its file, its line
(1-based, the header is line 1) and its column as a `DatasetError`.

Units: metres for coordinates, pixels (OpenCV: the centre of the top-left pixel is (0, 0)) for
image coordinates; quaternions are (w, x, y, z) of cam_from_world (images) or rig_from_world (frames).
"""

from __future__ import annotations

import codecs
import csv
import logging
import math
import numbers
import os
import re
import tempfile
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from ._float_text import cells_floats
from .camera import MODELS
from .errors import DatasetError, yaml_problem
from .files import write_csv_atomic, write_yaml_atomic
from .geo import (FAR_OUTSIDE_DEG, Geo, GeoError, crs_3d, default_origin, ecef_from_crs, enu_from_ecef,
                  outside_area_of_use, pyproj_crs)
from .geometry import quat_from_rotation, rotation_from_euler_zyx
from .trajectory import FORMATS, TrajectoryError, at_times, read_trajectory

log = logging.getLogger(__name__)

MANIFEST = "dataset.yaml"
CONTROL_POINTS = "control_points.csv"
GROUND_POINTS = "ground_points.csv"
IMAGES = "images.csv"
FRAMES = "frames.csv"
OBSERVATIONS = "observations.csv"
TRUTH = "truth"

STAGES = ("intrinsics", "extrinsics", "flight")
SPLITS = ("calib", "eval")
DEFAULT_MARKER_SIZE_M = 2.0

POINT_COLUMNS = ("point_id", "x", "y", "z")
#: Optional columns of control_points.csv and ground_points.csv: the point's survey sigma per axis (m),
#: and its vertical (z) sigma where the survey gives one apart (sigma_m is then that of x and y).
POINT_SIGMA = "sigma_m"
POINT_SIGMA_Z = "sigma_z_m"
PRIOR_CENTER = ("prior_x", "prior_y", "prior_z")
PRIOR_QUAT = ("prior_qw", "prior_qx", "prior_qy", "prior_qz")
IMAGE_COLUMNS = ("image", "camera", "stage", "split", "placement", "path")
FRAME_COLUMNS = ("frame", "group", "pos_x", "pos_y", "pos_z")
OBSERVATION_COLUMNS = ("image", "point_id", "u", "v")
RESULT_OBSERVATION_COLUMNS = ("image", "camera", "point_id", "u", "v")

_MANIFEST_KEYS = ("name", "description", "reference_camera", "cameras", "marker_size_m", "crs", "pos_crs", "origin",
                  "trajectory")
_TRAJECTORY_KEYS = ("path", "format")
#: frames.csv's optional time (s, the trajectory's time base) and INS attitude (deg; NED, the
#: trajectory's convention: ned_from_imu = Rz(heading) Ry(pitch) Rx(roll)).
FRAME_TIME = "time"
INS_ANGLES = ("ins_heading_deg", "ins_pitch_deg", "ins_roll_deg")
#: dataset.yaml `origin`'s keys: the computation frame's origin on WGS 84 (geo.py).
_ORIGIN_KEYS = ("lat_deg", "lon_deg", "h_m")
_CAMERA_KEYS = ("width", "height", "focal_px", "model")
_MIN_QUATERNION_NORM = 1e-6
#: A control field is collinear when its RMS spread across its best-fit line is below both this
#: fraction of the spread along it and COLLINEAR_SPREAD_M (survey noise of points on a line).
COLLINEAR_TOLERANCE = 1e-3
COLLINEAR_SPREAD_M = 0.01
#: How far (px) an observation may lie outside its image, whose pixels cover [-0.5, width - 0.5].
OBSERVATION_MARGIN_PX = 2.0
_PROGRESS_EVERY = 20


@dataclass(frozen=True)
class CameraSpec:
    """A camera as the manifest declares it: image size in pixels, an optional nominal focal (px) and
    its lens model (camera.MODELS: radial1, the paper's, by default; or opencv)."""

    width: int
    height: int
    focal_px: float | None
    model: str = "radial1"


# ------------------------------------------------------------------------------ dataset.yaml


@dataclass(frozen=True)
class _Manifest:
    name: str
    reference_camera: str
    cameras: dict[str, CameraSpec]
    marker_size_m: float
    description: str
    crs: str = ""
    pos_crs: str = ""
    origin: tuple[float, float, float] | None = None
    trajectory: tuple[str, str] | None = None  # (path relative to the dataset, format)


def _read_manifest(path: Path) -> _Manifest:
    if not path.is_file():
        raise DatasetError(path, "missing: every dataset needs this manifest (see docs/dataset.md)")
    try:
        data = yaml.safe_load(path.read_text(encoding="utf-8"))
    except UnicodeDecodeError:
        raise DatasetError(path, "is not UTF-8 text") from None
    except yaml.YAMLError as error:
        problem, line = yaml_problem(error)
        raise DatasetError(path, f"invalid YAML: {problem}", line) from None
    return _parse_manifest(data, path)


def _parse_manifest(data, path: Path) -> _Manifest:
    """Validate a manifest mapping (as YAML loads it); errors name `path`."""
    if not isinstance(data, dict):
        raise DatasetError(path, "expected a mapping with the keys name, reference_camera and cameras")
    _check_keys(data, _MANIFEST_KEYS, path, "")
    for key in ("name", "reference_camera", "cameras"):
        if key not in data:
            raise DatasetError(path, f"missing required key '{key}'")
    cameras = _parse_cameras(data["cameras"], path)
    reference = _text_value(data["reference_camera"], "reference_camera", path)
    if reference not in cameras:
        raise DatasetError(path, f"reference_camera '{reference}' is not one of the cameras ({', '.join(cameras)})")
    description = data.get("description")
    return _Manifest(
        name=_text_value(data["name"], "name", path),
        reference_camera=reference,
        cameras=cameras,
        marker_size_m=_positive(data.get("marker_size_m", DEFAULT_MARKER_SIZE_M), "marker_size_m", path),
        description="" if description is None else _text_value(description, "description", path, allow_empty=True),
        **_parse_crs_keys(data, path),
        trajectory=_parse_trajectory(data, path),
    )


def _parse_trajectory(data: dict, path: Path) -> tuple[str, str] | None:
    """dataset.yaml's trajectory: {path, format} (a relative path, a format of trajectory.FORMATS);
    it needs crs (its positions are geodetic)."""
    if "trajectory" not in data:
        return None
    entry = data["trajectory"]
    if not isinstance(entry, dict):
        raise DatasetError(path, f"trajectory must be a mapping with path and format, got {entry!r}")
    _check_keys(entry, _TRAJECTORY_KEYS, path, "trajectory: ")
    file = _text_value(entry.get("path"), "trajectory.path", path)
    kind = entry.get("format")
    if kind not in FORMATS:
        raise DatasetError(path, f"trajectory.format must be one of {', '.join(FORMATS)}, got {kind!r}")
    if Path(file).is_absolute():
        raise DatasetError(path, f"trajectory.path {file!r} must be relative to the dataset folder")
    if "crs" not in data:
        raise DatasetError(path, "trajectory is given without crs; its positions are WGS 84 latitude, longitude "
                           "and height, so the dataset needs a crs")
    return file, kind


def _parse_crs_keys(data: dict, path: Path) -> dict:
    """crs, pos_crs (default crs) and origin of a manifest, each CRS checked by pyproj; without crs,
    pos_crs and origin are errors (they would be ignored)."""
    if "crs" not in data:
        for key in ("pos_crs", "origin"):
            if key in data:
                raise DatasetError(path, f"{key} is given without crs; name the CRS of the points as crs")
        return {}
    crs = _text_value(data["crs"], "crs", path)
    pos_crs = _text_value(data["pos_crs"], "pos_crs", path) if "pos_crs" in data else crs
    for key, text in (("crs", crs), ("pos_crs", pos_crs)):
        try:
            crs_3d(text)
        except GeoError as error:
            raise DatasetError(path, f"{key}: {error}") from None
    return {"crs": crs, "pos_crs": pos_crs, "origin": _parse_origin(data["origin"], path) if "origin" in data else None}


def _parse_origin(data, path: Path) -> tuple[float, float, float]:
    if not isinstance(data, dict):
        raise DatasetError(path, f"origin must be a mapping with {', '.join(_ORIGIN_KEYS)}, got {data!r}")
    _check_keys(data, _ORIGIN_KEYS, path, "origin: ")
    values = []
    for key, limit in zip(_ORIGIN_KEYS, (90.0, 180.0, 1e5)):
        value = data.get(key)
        if isinstance(value, bool) or not isinstance(value, numbers.Real) or not abs(value) <= limit:
            raise DatasetError(path, f"origin.{key} must be a number within +-{limit:g}, got {value!r}")
        values.append(float(value))
    return tuple(values)


def _parse_cameras(data, path: Path) -> dict[str, CameraSpec]:
    if not isinstance(data, dict) or not data:
        raise DatasetError(path, "cameras must be a non-empty mapping: name -> {width, height, focal_px}")
    cameras = {}
    for name, spec in data.items():
        name = _text_value(name, "camera name", path)
        where = f"cameras.{name}"
        if not isinstance(spec, dict):
            raise DatasetError(path, f"{where} must be a mapping with width, height and optionally focal_px")
        _check_keys(spec, _CAMERA_KEYS, path, f"{where}: ")
        for key in ("width", "height"):
            if key not in spec:
                raise DatasetError(path, f"{where}: missing required key '{key}'")
        focal = spec.get("focal_px")
        model = spec.get("model", "radial1")
        if model not in MODELS:
            raise DatasetError(path, f"{where}.model must be one of {', '.join(MODELS)}, got {model!r}")
        cameras[name] = CameraSpec(
            width=_positive(spec["width"], f"{where}.width", path, integer=True),
            height=_positive(spec["height"], f"{where}.height", path, integer=True),
            focal_px=None if focal is None else _positive(focal, f"{where}.focal_px", path),
            model=model,
        )
    return cameras


def _check_keys(data: dict, known: Sequence[str], path: Path, where: str) -> None:
    for key in data:
        if key not in known:
            raise DatasetError(path, f"{where}unknown key '{key}' (known keys: {', '.join(known)})")


def _text_value(value, key: str, path: Path, allow_empty: bool = False) -> str:
    if not isinstance(value, str):
        raise DatasetError(path, f"{key} must be a string, got {value!r}; quote it in the YAML")
    if not value.strip() and not allow_empty:
        raise DatasetError(path, f"{key} must not be empty")
    return value.strip()


def _positive(value, key: str, path: Path, integer: bool = False):
    """`value` as a positive int (integer=True) or positive finite float, else a DatasetError."""
    kind = numbers.Integral if integer else numbers.Real
    if isinstance(value, bool) or not isinstance(value, kind) or not math.isfinite(value) or value <= 0:
        kind = "integer" if integer else "number"
        raise DatasetError(path, f"{key} must be a positive {kind}, got {value!r}")
    return int(value) if integer else float(value)


def _manifest_dict(manifest: _Manifest) -> dict:
    """The manifest as plain YAML-able data, keys in the documented order."""
    cameras = {}
    for name, spec in manifest.cameras.items():
        cameras[name] = {"width": spec.width, "height": spec.height}
        if spec.focal_px is not None:
            cameras[name]["focal_px"] = spec.focal_px
        if spec.model != "radial1":
            cameras[name]["model"] = spec.model
    data = {"name": manifest.name}
    if manifest.description:
        data["description"] = manifest.description
    data.update(reference_camera=manifest.reference_camera, cameras=cameras, marker_size_m=manifest.marker_size_m)
    if manifest.crs:
        data.update(crs=manifest.crs, pos_crs=manifest.pos_crs)
    if manifest.origin is not None:
        data["origin"] = dict(zip(_ORIGIN_KEYS, manifest.origin))
    if manifest.trajectory is not None:
        data["trajectory"] = dict(zip(_TRAJECTORY_KEYS, manifest.trajectory))
    return data


# ------------------------------------------------------------------------------ CSV tables


class Table:
    """A CSV file as stripped strings, one row per data line.

    path; columns: {name: (n,) its cells, str}, in the header's order; lines: (n,) the 1-based file line of
    every row. A column is converted when first asked for (`text`, `strings`, `floats`, `codes`; `cells`: all
    of them as an (n, k) DataFrame of str, RangeIndex), so that a large file's readers pay for the columns
    they use alone.
    """

    def __init__(self, path: Path, columns: dict[str, Sequence[str]], lines: np.ndarray):
        self.path, self.columns, self.lines = path, columns, lines
        self._text: dict[str, np.ndarray] = {}
        self._codes: dict[str, tuple[np.ndarray, np.ndarray]] = {}

    def __len__(self) -> int:
        return len(self.lines)

    def __contains__(self, column: str) -> bool:
        return column in self.columns

    @property
    def cells(self) -> pd.DataFrame:
        """(n, k) DataFrame of str, RangeIndex: every column."""
        return pd.DataFrame({column: self.strings(column) for column in self.columns})

    def error(self, message: str, row: int | None = None) -> DatasetError:
        return DatasetError(self.path, message, None if row is None else int(self.lines[row]))

    def check(self, bad: np.ndarray, message: Callable[[int], str]) -> None:
        """Raise for the first row where `bad` (n,) is true, with `message(row)`."""
        bad = np.asarray(bad, dtype=bool)
        if bad.any():
            row = int(np.argmax(bad))
            raise self.error(message(row), row)

    def text(self, column: str) -> np.ndarray:
        """(n,) object array of the column's strings; all empty when the column is absent."""
        if column not in self.columns:
            return np.full(len(self), "", dtype=object)
        if column not in self._text:  # fromiter: np.array would look into every str for a sequence
            self._text[column] = np.fromiter(self.columns[column], dtype=object, count=len(self))
        return self._text[column]

    def strings(self, column: str) -> pd.Series:
        """(n,) Series of str (RangeIndex) of the column's strings, made of a new str object per distinct value
        (`codes`; observations.csv's image and point id: a few thousand objects in place of a million cells).
        None of the file's cells outlives the table: Python returns a region of its small objects to the system
        only once every object in it is gone, and a cell kept would hold its neighbours' memory (the cells of a
        line's 1.4 million observations: 0.4 GB)."""
        codes, distinct = self.codes(column)
        return _strings(_copied(distinct).take(codes))

    def codes(self, column: str) -> tuple[np.ndarray, np.ndarray]:
        """(codes (n,), distinct (d,)): pd.factorize of the column's strings (hashed once per table)."""
        if column not in self._codes:
            self._codes[column] = factorized(self.text(column))
        return self._codes[column]

    def required_text(self, column: str) -> np.ndarray:
        values = self.text(column)
        if column in self._codes:  # its distinct strings are known: compare those alone
            codes, distinct = self._codes[column]
            empty = np.flatnonzero(distinct == "")
            self.check(codes == (empty[0] if len(empty) else -1), lambda row: f"column {column} is empty")
        else:
            self.check(values == "", lambda row: f"column {column} is empty")
        return values

    def floats(self, column: str, optional: bool = False) -> np.ndarray:
        """(n,) floats of the column; NaN for empty cells when `optional`, else every cell must be finite.
        A column with no empty or bad cell is converted from its cells straight away (float() of each, read by
        the compiled `_float_text.cells_floats`); the others cell by cell (`_parse_floats`)."""
        values = _all_floats(self.columns.get(column), len(self))
        if values is None:
            text = self.text(column)
            values = _parse_floats(text)
            bad = ~np.isfinite(values) & ((text != "") if optional else True)
        else:  # no cell is empty
            text, bad = self.columns[column], ~np.isfinite(values)
        self.check(bad, lambda row: f"column {column}: {text[row]!r} is not a finite number"
                   if text[row] else f"column {column} is empty; expected a number")
        return values

    def check_unique(self, columns: Sequence[str], what: str) -> None:
        """`first_rows`' check alone: a repeated key raises naming both lines (hashed in one pass per
        column, `codes`; the first repeat is then named by `first_rows`)."""
        if _repeated([self.codes(column) for column in columns]):
            self.first_rows(columns, what)

    def first_rows(self, columns: Sequence[str], what: str) -> dict:
        """Map from key (a value, or a tuple for several columns) to its row; duplicates raise naming both lines."""
        seen = {}
        keys = zip(*(self.text(column) for column in columns))
        for row, key in enumerate(keys):
            key = key[0] if len(columns) == 1 else key
            if key in seen:
                raise self.error(f"duplicate {what} {key!r} (first on line {self.lines[seen[key]]})", row)
            seen[key] = row
        return seen

    def extra_columns(self, known: Sequence[str]) -> list[str]:
        return [column for column in self.columns if column not in known]


def _repeated(parts: Sequence[tuple[np.ndarray, np.ndarray]]) -> bool:
    """Whether a key repeats, of keys given by each part's (codes (n,), distinct) (pd.factorize's)."""
    key = np.zeros(len(parts[0][0]), dtype=np.int64)
    for codes, distinct in parts:
        key = pd.factorize(key * len(distinct) + codes)[0]  # the keys' places, below n: no overflow
    return int(key.max(initial=-1)) + 1 < len(key)


#: Values `factorized` looks at to tell whether a column runs in blocks of one value.
_RUN_SAMPLE = 1024


def factorized(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """pd.factorize(values) of (n,) str objects: (codes (n,), distinct (d,)). A column that runs in blocks of
    one value (observations.csv's image, every marker of an image in a row) is compared with its neighbours
    and only each block's first value hashed: the same codes and distinct values (in order of first
    appearance), at a fraction of the hashing of every cell."""
    sample = values[:_RUN_SAMPLE]
    if len(values) <= _RUN_SAMPLE or 4 * np.count_nonzero(sample[1:] != sample[:-1]) >= len(sample):
        return pd.factorize(values)
    firsts = np.flatnonzero(np.r_[True, values[1:] != values[:-1]])
    codes, distinct = pd.factorize(values[firsts])
    return np.repeat(codes, np.diff(np.r_[firsts, len(values)])), distinct


def _copied(values) -> np.ndarray:
    """(k,) object array of new str objects equal to `values` (k,) str."""
    return np.fromiter((value.encode().decode() for value in values), dtype=object, count=len(values))


def _all_floats(cells: Sequence[str] | None, n: int) -> np.ndarray | None:
    """(n,) float() of every cell, None where one is not a number (an empty cell too) or there are none."""
    return None if cells is None else cells_floats(cells, n)


def _parse_float(cell: str) -> float:
    try:
        return float(cell)
    except ValueError:
        return math.nan


def _parse_floats(text: np.ndarray) -> np.ndarray:
    """(n,) `_parse_float` of each cell of text (n,) object: the non-empty cells converted by numpy
    in one call (which calls float() on each), cell by cell only where one is not a number."""
    values = np.full(len(text), np.nan)
    given = text != ""
    try:
        values[given] = text[given].astype(float)
    except ValueError:
        values = np.array([_parse_float(cell) for cell in text], dtype=float)
    return values


def read_table(path: Path, required: Sequence[str], optional: Sequence[str] = ()) -> Table:
    """Read a CSV file with a header holding at least `required` columns (blank lines are skipped)."""
    if not path.is_file():
        raise DatasetError(path, "missing")
    plain = _read_plain(path)
    if plain is not None:
        header, columns = plain
        _check_header(path, header, required)
        return Table(path, dict(zip(header, columns)), np.arange(2, len(columns[0]) + 2))
    try:
        header, rows, lines = _read_rows(path)
    except UnicodeDecodeError:
        raise DatasetError(path, "is not UTF-8 text") from None
    if header is None:
        raise DatasetError(path, f"is empty; expected the header {','.join(required)}")
    _check_header(path, header, required)
    columns = list(zip(*rows)) if rows else [()] * len(header)
    return Table(path, dict(zip(header, columns)), np.asarray(lines, dtype=int))


#: The ASCII whitespace that str.strip() removes, but the line end: a file with one has its cells stripped.
_ASCII_BLANKS = tuple(c.encode() for c in " \t\x0b\x0c\x1c\x1d\x1e\x1f")


def _read_plain(path: Path) -> tuple[list[str], list[list[str]]] | None:
    """The header and the columns' stripped cells of a plain CSV file, split in one pass: UTF-8,
    lines ended by "\n" alone, no quote or NUL, no blank line, at least two columns, every line
    with the header's number of fields, none longer than the csv module's field limit. Its data
    lines are lines 2, 3, ... None for any other file: `_read_rows` reads it, and names its faults
    as before (the csv module's reading of a plain file is this split)."""
    data = path.read_bytes()
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError:
        return None
    if not text or '"' in text or "\r" in text or "\0" in text:
        return None
    body = np.frombuffer(data, np.uint8)[len(codecs.BOM_UTF8) if data.startswith(codecs.BOM_UTF8) else 0:]
    separators = np.flatnonzero((body == ord(",")) | (body == ord("\n")))
    line_ends = np.flatnonzero(body[separators] == ord("\n"))  # among the separators
    if body[-1] != ord("\n"):
        line_ends = np.append(line_ends, len(separators))
    commas = np.diff(line_ends, prepend=-1) - 1  # each line's
    ends = np.append(separators, len(body))[line_ends]
    if commas[0] == 0 or (commas != commas[0]).any() or np.diff(ends, prepend=-1).max() > csv.field_size_limit():
        return None
    width = int(commas[0]) + 1
    cells = text.replace("\n", ",").split(",")
    if text.endswith("\n"):
        cells.pop()
    if not text.isascii() or any(blank in data for blank in _ASCII_BLANKS):
        cells = [cell.strip() for cell in cells]
    return cells[:width], [cells[width + k::width] for k in range(width)]


def _read_rows(path: Path) -> tuple[list[str] | None, list[list[str]], list[int]]:
    header, rows, lines = None, [], []
    with path.open(newline="", encoding="utf-8-sig") as file:
        reader = csv.reader(file)
        try:
            for record in reader:
                if len(record) <= 1 and not "".join(record).strip():
                    continue  # blank line
                record = [cell.strip() for cell in record]
                if header is None:
                    header = record
                elif len(record) != len(header):
                    raise DatasetError(path, f"{len(record)} fields, the header has {len(header)}", reader.line_num)
                else:
                    rows.append(record)
                    lines.append(reader.line_num)
        except csv.Error as error:
            raise DatasetError(path, f"malformed CSV: {error}", reader.line_num) from None
    return header, rows, lines


def _check_header(path: Path, header: list[str], required: Sequence[str]) -> None:
    seen = set()
    for column in header:
        if not column:
            raise DatasetError(path, "a column of the header has no name", 1)
        if column in seen:
            raise DatasetError(path, f"column {column} appears twice in the header", 1)
        seen.add(column)
    missing = [column for column in required if column not in seen]
    if missing:
        raise DatasetError(path, f"missing column(s) {', '.join(missing)} (expected {','.join(required)})", 1)


def _group(table: Table, columns: Sequence[str]) -> np.ndarray:
    """(n, k) floats of a column group that each row gives entirely or not at all (NaN rows)."""
    values = np.column_stack([table.floats(column, optional=True) for column in columns])
    given = ~np.isnan(values)
    partial = given.any(axis=1) & ~given.all(axis=1)
    table.check(partial, lambda row: f"{', '.join(columns)} must be given all or none; this row gives only "
                + ", ".join(c for c, g in zip(columns, given[row]) if g))
    return values


def _quaternions(table: Table, columns: Sequence[str]) -> np.ndarray:
    """(n, 4) unit quaternions (w, x, y, z) of a column group, NaN rows where absent."""
    q = _group(table, columns)
    norm = np.linalg.norm(q, axis=1)
    table.check(norm <= _MIN_QUATERNION_NORM,
                lambda row: f"{', '.join(columns)}: quaternion norm {norm[row]:.3g} must be > {_MIN_QUATERNION_NORM:g}")
    # Leave quaternions that are unit to rounding alone, so that loading a written dataset is exact.
    rescale = np.abs(norm - 1.0) > 4 * np.finfo(float).eps
    q[rescale] /= norm[rescale, None]
    return q


def _frame(table: Table, columns: dict, known: Sequence[str]) -> pd.DataFrame:
    """DataFrame of the converted `columns` followed by the table's extra columns (as strings)."""
    frame = pd.DataFrame(columns, index=pd.RangeIndex(len(table)))
    for column in table.extra_columns(known):
        frame[column] = table.strings(column)
    return frame


def _strings(values) -> pd.Series:
    return pd.Series(values, dtype=str)


# ------------------------------------------------------------------------------ the files


def _read_points(path: Path) -> tuple[pd.DataFrame, Table]:
    """Points indexed by point_id (str) with float columns x, y, z, and sigma_m, sigma_z_m where the
    file has them (NaN in their empty cells) (+ extras), and the table read."""
    table = read_table(path, POINT_COLUMNS, (POINT_SIGMA, POINT_SIGMA_Z))
    table.required_text("point_id")  # validates: every row has a point id
    table.check_unique(["point_id"], "point id")
    columns = {"point_id": table.strings("point_id"), **{axis: table.floats(axis) for axis in "xyz"}}
    known = POINT_COLUMNS
    for name in (POINT_SIGMA, POINT_SIGMA_Z):
        if name in table:
            sigma = table.floats(name, optional=True)
            table.check(sigma < 0, lambda row: f"column {name}: {sigma[row]} is negative; expected a survey "
                        "sigma in metres (or an empty cell)")
            columns[name], known = sigma, (*known, name)
    return _frame(table, columns, known).set_index("point_id"), table


def point_sigma(points: pd.DataFrame, point_ids) -> np.ndarray:
    """(n, 3) the survey sigma (m) along x, y, z of each of point_ids (n,) in points (indexed by
    point_id): `sigma_m`, and `sigma_z_m` along z where given; NaN where the file has no such
    column, the cell is empty or the point is not there."""
    sigma = np.full((len(point_ids), 3), np.nan)
    if POINT_SIGMA in points.columns:
        sigma[:] = points[POINT_SIGMA].reindex(point_ids).to_numpy(float)[:, None]
    if POINT_SIGMA_Z in points.columns:
        vertical = points[POINT_SIGMA_Z].reindex(point_ids).to_numpy(float)
        sigma[:, 2] = np.where(np.isnan(vertical), sigma[:, 2], vertical)
    return sigma


def largest_point_sigma(points: pd.DataFrame, point_ids) -> np.ndarray:
    """(n,) the largest of each point's survey sigmas along x, y, z (`point_sigma`), NaN where none is
    given (the calibration estimates it): the calibration's survey term, one sigma for all three axes."""
    return np.fmax.reduce(point_sigma(points, point_ids), axis=1)


def _check_disjoint(control: Table, ground: Table) -> None:
    control_rows = control.first_rows(["point_id"], "point id")
    ids = ground.text("point_id")
    shared = np.array([pid in control_rows for pid in ids], dtype=bool)
    ground.check(shared, lambda row: f"point id {ids[row]!r} is also in {CONTROL_POINTS}, "
                 f"line {control.lines[control_rows[ids[row]]]}")


def _check_field_geometry(path: Path, points: np.ndarray) -> None:
    """A calibration field must span a plane (as a chessboard does) or a volume: points (n, 3) that
    coincide or lie on one line give no pose, so they are refused here rather than deep in PnPf."""
    if len(points) < 3:
        return  # too few to be a field at all; the stages that use the field say how many they need
    spread = np.linalg.svd(points - points.mean(axis=0), compute_uv=False) / np.sqrt(len(points))
    if spread[0] <= 1e-9 * max(1.0, float(np.abs(points).max())):
        raise DatasetError(path, f"all {len(points)} control points coincide; the calibration field must "
                           "span a plane or a volume")
    if spread[1] <= COLLINEAR_TOLERANCE * spread[0] and spread[1] <= COLLINEAR_SPREAD_M:
        raise DatasetError(path, f"the {len(points)} control points are collinear (spread {spread[1]:.3g} m "
                           f"across their line, {spread[0]:.3g} m along it); the calibration field must span "
                           "a plane or a volume")


def _empty_points() -> pd.DataFrame:
    frame = pd.DataFrame({"point_id": _strings([]), **{axis: np.zeros(0) for axis in "xyz"}})
    return frame.set_index("point_id")


def _read_images(path: Path, root: Path, cameras: dict[str, CameraSpec]) -> tuple[pd.DataFrame, Table]:
    """images.csv as a DataFrame (columns IMAGE_COLUMNS, PRIOR_CENTER, PRIOR_QUAT, extras) and its table."""
    table = read_table(path, IMAGE_COLUMNS, PRIOR_CENTER + PRIOR_QUAT)
    table.required_text("image")  # validates: every row has an image id
    table.check_unique(["image"], "image id")
    camera = table.required_text("camera")
    table.check(~np.isin(camera, list(cameras)),
                lambda row: f"unknown camera '{camera[row]}' ({MANIFEST} has {', '.join(cameras)})")
    stage = table.text("stage")
    table.check(~np.isin(stage, STAGES),
                lambda row: f"stage {stage[row]!r} is not one of {', '.join(STAGES)}")
    _check_split(table, stage)
    _check_placement(table, stage, camera)
    _check_paths(table, root)
    center = _group(table, PRIOR_CENTER)
    quat = _quaternions(table, PRIOR_QUAT)
    columns = {name: table.strings(name) for name in IMAGE_COLUMNS}
    columns.update(zip(PRIOR_CENTER, center.T))
    columns.update(zip(PRIOR_QUAT, quat.T))
    return _frame(table, columns, IMAGE_COLUMNS + PRIOR_CENTER + PRIOR_QUAT), table


def _check_split(table: Table, stage: np.ndarray) -> None:
    split = table.text("split")
    intrinsics = stage == "intrinsics"
    table.check(intrinsics & (split == ""), lambda row: "split is empty; intrinsics images need calib or eval")
    table.check(intrinsics & ~np.isin(split, SPLITS), lambda row: f"split {split[row]!r} is not calib or eval")
    table.check(~intrinsics & (split != ""),
                lambda row: f"split {split[row]!r} given for a {stage[row]} image; split is for intrinsics images only")


def _check_placement(table: Table, stage: np.ndarray, camera: np.ndarray) -> None:
    placement = table.text("placement")
    rig = stage != "intrinsics"
    table.check(rig & (placement == ""), lambda row: f"placement is empty; {stage[row]} images need "
                + ("the frame id" if stage[row] == "flight" else "a rig placement id"))
    if not _repeated([pd.factorize(values[rig]) for values in (stage, placement, camera)]):
        return  # hashed in one pass per column; a repeat is named by the loop below
    seen = {}
    for row in np.flatnonzero(rig):
        key = (stage[row], placement[row], camera[row])
        if key in seen:
            raise table.error(f"camera {camera[row]} has two images at {stage[row]} placement {placement[row]!r} "
                              f"(first on line {table.lines[seen[key]]})", row)
        seen[key] = row


def _check_paths(table: Table, root: Path) -> None:
    image, path = table.text("image"), table.text("path")
    given = path != ""
    if not given.any():  # observation-only images: nothing to look at
        return
    table.check([p != "" and Path(p).is_absolute() for p in path],
                lambda row: f"image {image[row]!r}: path {path[row]!r} must be relative to the dataset folder")
    table.check([p != "" and not (root / p).is_file() for p in path],
                lambda row: f"image {image[row]!r}: {_no_file(path[row])}")


def _no_file(path: str) -> str:
    return f"file {path!r} does not exist"


def _read_frames(path: Path) -> pd.DataFrame:
    """frames.csv as a DataFrame (columns FRAME_COLUMNS, NaN where a row gives no pos_*, PRIOR_QUAT,
    extras) and its table."""
    table = read_table(path, FRAME_COLUMNS[:2], FRAME_COLUMNS[2:] + PRIOR_QUAT)
    table.required_text("frame")  # validates: every row has a frame id
    table.check_unique(["frame"], "frame id")
    columns = {"frame": table.strings("frame"), "group": table.strings("group")}
    columns.update(zip(FRAME_COLUMNS[2:], _group(table, FRAME_COLUMNS[2:]).T))
    columns.update(zip(PRIOR_QUAT, _quaternions(table, PRIOR_QUAT).T))
    return _frame(table, columns, FRAME_COLUMNS + PRIOR_QUAT), table


# ------------------------------------------------------------------------------ coordinate reference systems


def _dataset_geo(manifest: _Manifest, control: pd.DataFrame, table: Table) -> Geo | None:
    """The dataset's Geo (None without crs); its origin dataset.yaml's, else the control points'
    mean (geo.default_origin)."""
    if not manifest.crs:
        return None
    for key in ("crs", "pos_crs"):
        text = getattr(manifest, key)
        if len(pyproj_crs(text).axis_info) < 3:
            log.info("%s %s is 2-D: its z is taken as the ellipsoidal height", key, text)
    xyz = control[list(POINT_COLUMNS[1:])].to_numpy(float)
    origin = manifest.origin or default_origin(_ecef(manifest.crs, "crs", table, xyz, POINT_COLUMNS[1:]))
    return Geo(manifest.crs, manifest.pos_crs, origin)


def _in_computation_frame(frame: pd.DataFrame, columns: Sequence[str], table: Table, geo: Geo,
                          pos: bool = False) -> pd.DataFrame:
    """`frame` (rows as the `table` read) with its coordinate `columns` (x, y, z in `crs`, or in
    `pos_crs` with pos) converted to the computation frame where a row gives them (NaN rows kept)."""
    xyz = frame[list(columns)].to_numpy(float, copy=True)
    given = np.isfinite(xyz).all(axis=1)
    if not given.any():
        return frame
    key = "pos_crs" if pos else "crs"
    ecef = _ecef(getattr(geo, key), key, table, xyz, columns, given)
    xyz[given] = enu_from_ecef(geo.origin, ecef)
    out = frame.copy()
    out[list(columns)] = xyz
    return out


def _ecef(crs: str, key: str, table: Table, xyz: np.ndarray, columns: Sequence[str],
          given: np.ndarray | None = None) -> np.ndarray:
    """(k, 3) geocentric coordinates of the rows `given` (n,) (default all) of xyz (n, 3) in `crs`
    (dataset.yaml's `key`). A row pyproj cannot convert, or further than FAR_OUTSIDE_DEG outside
    the CRS's area of use, is an error naming its line; rows outside it nearer, a warning."""
    rows = np.flatnonzero(np.ones(len(xyz), bool) if given is None else given)
    names = ", ".join(columns)
    try:
        ecef = ecef_from_crs(crs, xyz[rows])
    except GeoError as error:
        raise table.error(f"{names} in {key} {crs!r}: {error}", None if error.row is None else rows[error.row]) from None
    distance, area = outside_area_of_use(crs, ecef)
    far = np.zeros(len(xyz), bool)
    far[rows] = distance > FAR_OUTSIDE_DEG
    table.check(far, lambda row: f"{names} ({', '.join(f'{v:.10g}' for v in xyz[row])}) lie "
                f"{distance[np.searchsorted(rows, row)]:.3g} deg outside the area of use of {key} {crs!r}, "
                f"{area}; are they in that CRS?")
    if (distance > 0).any():
        first = int(table.lines[rows[int(np.argmax(distance > 0))]])
        log.warning("%s: %d row(s) lie outside the area of use of %s %r (%s; first on line %d, at most %.3g deg "
                    "outside)", table.path, int((distance > 0).sum()), key, crs, area, first, distance.max())
    return ecef


def _positions_and_attitudes(root: Path, frames: pd.DataFrame, table: Table, geo: Geo | None,
                             trajectory: tuple[str, str] | None) -> pd.DataFrame:
    """`frames` with every row's POS position (pos_*, else interpolated at its time) and, where its
    prior_q* are empty, the INS attitude of its INS_ANGLES or of the trajectory, in the frame of
    `geo` (the computation frame)."""
    pos = frames[list(FRAME_COLUMNS[2:])].to_numpy(float, copy=True)
    missing = ~np.isfinite(pos).all(axis=1)
    time = table.floats(FRAME_TIME, optional=True)
    names = frames["frame"].to_numpy(object)
    table.check(missing & np.isnan(time), lambda row: f"frame {names[row]!r} gives neither {', '.join(FRAME_COLUMNS[2:])} "
                f"nor {FRAME_TIME}")
    angles = _group(table, INS_ANGLES)
    quat = frames[list(PRIOR_QUAT)].to_numpy(float, copy=True)
    from_angles = ~np.isfinite(quat).all(axis=1) & np.isfinite(angles).all(axis=1)
    needs_trajectory = missing | (~np.isfinite(quat).all(axis=1) & ~from_angles & ~np.isnan(time)
                                  & (trajectory is not None))
    if geo is None and (missing.any() or from_angles.any()):
        row = int(np.argmax(missing | from_angles))
        raise table.error(f"frame {names[row]!r}: {FRAME_TIME} and {', '.join(INS_ANGLES)} need dataset.yaml's crs "
                          "(they are geodetic)", row)
    ned_from_imu = np.full((len(frames), 3, 3), np.nan)
    ned_from_imu[from_angles] = rotation_from_euler_zyx(np.radians(angles[from_angles]))
    if needs_trajectory.any():
        if trajectory is None:
            row = int(np.argmax(missing))
            raise table.error(f"frame {names[row]!r} gives {FRAME_TIME} without pos_*, and dataset.yaml names no "
                              "trajectory", row)
        ecef, attitude = _interpolated(root, trajectory, table, time, needs_trajectory, names)
        rows = np.flatnonzero(needs_trajectory)
        pos[rows[missing[rows]]] = enu_from_ecef(geo.origin, ecef[missing[rows]])
        chosen = ~np.isfinite(quat[rows]).all(axis=1) & ~from_angles[rows]
        ned_from_imu[rows[chosen]] = attitude[chosen]
    given = np.isfinite(ned_from_imu).all(axis=(1, 2))
    if given.any():  # INS = imu_from_world = (world_from_ned @ ned_from_imu)^T
        world_from_ned = np.swapaxes(geo.ned_from_enu(pos[given]), 1, 2)
        quat[given] = quat_from_rotation(np.swapaxes(world_from_ned @ ned_from_imu[given], 1, 2))
    out = frames.copy()
    out[list(FRAME_COLUMNS[2:])] = pos
    out[list(PRIOR_QUAT)] = quat
    return out


def _interpolated(root: Path, trajectory: tuple[str, str], table: Table, time: np.ndarray, rows: np.ndarray,
                  names: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Geocentric positions and ned_from_imu (k, 3, 3) of the frames `rows` (n,) at their `time`
    (n,), from the trajectory file; errors name the file's record or the frame's line."""
    path = root / trajectory[0]
    if not path.is_file():
        raise DatasetError(path, "missing (dataset.yaml's trajectory.path)")
    try:
        samples = read_trajectory(path, trajectory[1], read_table)
    except TrajectoryError as error:  # its message names the record (sbet) or the line (csv)
        raise DatasetError(path, str(error)) from None
    chosen = np.flatnonzero(rows)
    try:
        return at_times(samples, time[chosen])
    except TrajectoryError as error:
        row = int(chosen[error.index])
        raise table.error(f"frame {names[row]!r}: {error} ({trajectory[0]})", row) from None


def _empty_frames() -> pd.DataFrame:
    columns = {"frame": _strings([]), "group": _strings([])}
    columns.update({name: np.zeros(0) for name in FRAME_COLUMNS[2:] + PRIOR_QUAT})
    return pd.DataFrame(columns)


def _read_observations(path: Path, camera_of: dict[str, str], cameras: dict[str, CameraSpec], point_ids,
                       with_camera: bool) -> tuple[pd.DataFrame, np.ndarray]:
    """Observations (image, [camera,] point_id, u, v, extras) checked against images, points and
    the image area of each image's camera, and the distinct images (k,) they are on."""
    names = RESULT_OBSERVATION_COLUMNS if with_camera else OBSERVATION_COLUMNS
    table = read_table(path, names)
    image_code, image_names = table.codes("image")  # each distinct image and point id looked up once
    image = table.required_text("image")
    image_camera = np.fromiter(map(camera_of.get, image_names), dtype=object, count=len(image_names))  # None: unknown
    table.check(pd.isna(image_camera)[image_code], lambda row: f"unknown image {image[row]!r} (not in {IMAGES})")
    if with_camera:
        camera = table.required_text("camera")
        table.check(image_camera[image_code] != camera, lambda row: f"camera {camera[row]!r} of image "
                    f"{image[row]!r} is {camera_of[image[row]]!r} in {IMAGES}")
    point_code, point_names = table.codes("point_id")
    point_id = table.required_text("point_id")
    table.check(~pd.Index(point_names).isin(point_ids)[point_code],
                lambda row: f"unknown point id {point_id[row]!r} (not in {CONTROL_POINTS} or {GROUND_POINTS})")
    table.check_unique(["image", "point_id"], "observation (image, point_id)")
    columns = {name: table.strings(name) for name in names if name not in ("u", "v")}
    columns.update(u=table.floats("u"), v=table.floats("v"))
    sizes = np.array([(spec.width, spec.height) for spec in cameras.values()], dtype=float).reshape(-1, 2)
    size = sizes[pd.Index(list(cameras)).get_indexer(image_camera)[image_code]]
    _check_inside_images(table, image, columns["u"], columns["v"], size)
    return _frame(table, {name: columns[name] for name in names}, names), image_names


def _check_inside_images(table: Table, image: np.ndarray, u: np.ndarray, v: np.ndarray, size: np.ndarray) -> None:
    """Every pixel (u, v) (n,) within OBSERVATION_MARGIN_PX of its image (n,) of size (n, 2) (width, height px)."""
    low, high = -0.5 - OBSERVATION_MARGIN_PX, size - 0.5 + OBSERVATION_MARGIN_PX
    outside = (u < low) | (u > high[:, 0]) | (v < low) | (v > high[:, 1])
    table.check(outside, lambda row: f"observation ({u[row]:.6g}, {v[row]:.6g}) lies outside image "
                f"{image[row]!r} ({int(size[row, 0])}x{int(size[row, 1])} px)")


def _empty_observations() -> pd.DataFrame:
    return pd.DataFrame({"image": _strings([]), "point_id": _strings([]), "u": np.zeros(0), "v": np.zeros(0)})


def table_stamps(root: Path) -> str:
    """The dataset folder's tables (its *.csv files, the manifest and the trajectory file it names)
    by name, size and modification time: what a load of `root` reads, so that a copy cut from a load
    (slices.py) is known stale when one of them changes, appears or goes."""
    stamps = ";".join(f"{path.name}:{file_stamp(path)}" for path in sorted(root.glob("*.csv")) + [root / MANIFEST])
    trajectory = _trajectory_path(root / MANIFEST)
    return stamps if trajectory is None else f"{stamps};{trajectory}:{file_stamp(root / trajectory)}"


def _trajectory_path(manifest: Path) -> str | None:
    """The manifest's trajectory.path where it reads as one (None otherwise: the load says why)."""
    try:
        entry = (yaml.safe_load(manifest.read_text(encoding="utf-8")) or {}).get("trajectory")
    except (OSError, ValueError, yaml.YAMLError, AttributeError):
        return None
    path = entry.get("path") if isinstance(entry, dict) else None
    return path if isinstance(path, str) else None


def file_stamp(path: Path) -> str:
    """A file's size and modification time (ns), 'None' where there is no such file."""
    stat = path.stat() if path.is_file() else None
    return str(stat and (stat.st_size, stat.st_mtime_ns))


# ------------------------------------------------------------------------------ Dataset


@dataclass(eq=False, repr=False)
class Dataset:
    """A validated dataset directory (docs/dataset.md). Load with `Dataset.load(path)`.

    control_points, ground_points: index point_id (str), columns x, y, z (float, metres) + extras.
    images: image, camera, stage, split, placement, path (str, '' when empty), prior_x, prior_y,
        prior_z, prior_qw, prior_qx, prior_qy, prior_qz (float, NaN where absent) + extras.
    frames: frame, group (str), pos_x, pos_y, pos_z, prior_qw..prior_qz (float) + extras.
    observations: image, point_id (str), u, v (float, pixels) + extras.
    Extra columns of the CSV files are kept as strings after the documented ones.
    stamps: the tables as they were when the load began (`table_stamps`); part: '' for the whole
    dataset, else what of it a job's slice holds (`restricted`, slices.py).
    geo: dataset.yaml's crs, pos_crs and the computation frame's origin (geo.py), None without crs.
    With it every coordinate above (points, prior_x..z, pos_x..z) is in the computation frame.
    """

    root: Path
    name: str
    reference_camera: str
    cameras: dict[str, CameraSpec]
    marker_size_m: float
    description: str
    control_points: pd.DataFrame
    ground_points: pd.DataFrame
    images: pd.DataFrame
    frames: pd.DataFrame
    observations: pd.DataFrame
    image_lines: dict[str, int] = field(default_factory=dict)  # image id -> its line in images.csv
    stamps: str = ""
    part: str = ""
    geo: Geo | None = None
    _positions: dict = field(default_factory=dict, init=False, repr=False)  # `_rows`' groups, made once

    @classmethod
    def load(cls, path: str | Path) -> Dataset:
        """Read and validate the dataset directory `path`; raises DatasetError naming file and line."""
        root = Path(path).absolute()
        if not root.is_dir():
            raise DatasetError(root, "is not a dataset directory")
        stamps = table_stamps(root)  # before reading: a table changed meanwhile makes the stamps stale
        manifest = _read_manifest(root / MANIFEST)
        control, control_table = _read_points(root / CONTROL_POINTS)
        if control.empty:
            raise DatasetError(root / CONTROL_POINTS, "has no points; at least one control point is needed")
        geo = _dataset_geo(manifest, control, control_table)
        if geo is not None:
            control = _in_computation_frame(control, POINT_COLUMNS[1:], control_table, geo)
        _check_field_geometry(root / CONTROL_POINTS, control[["x", "y", "z"]].to_numpy(float))
        ground = _empty_points()
        if (root / GROUND_POINTS).exists():
            ground, ground_table = _read_points(root / GROUND_POINTS)
            _check_disjoint(control_table, ground_table)
            if geo is not None:
                ground = _in_computation_frame(ground, POINT_COLUMNS[1:], ground_table, geo)
        images, image_table = _read_images(root / IMAGES, root, manifest.cameras)
        if geo is not None:
            images = _in_computation_frame(images, PRIOR_CENTER, image_table, geo, pos=True)
        frames = _load_frames(root, images, image_table, geo, manifest.trajectory)
        observations, observed = _empty_observations(), np.zeros(0, dtype=object)
        if (root / OBSERVATIONS).exists():
            camera_of = camera_of_images(images)
            points = pd.concat([control.index.to_series(), ground.index.to_series()])
            observations, observed = _read_observations(root / OBSERVATIONS, camera_of, manifest.cameras, points,
                                                        with_camera=False)
        _check_sources(image_table, images, observed)
        return cls(
            root=root, name=manifest.name, reference_camera=manifest.reference_camera, cameras=manifest.cameras,
            marker_size_m=manifest.marker_size_m, description=manifest.description,
            control_points=control, ground_points=ground, images=images, frames=frames, observations=observations,
            image_lines=dict(zip(images["image"].to_numpy(object), image_table.lines.tolist())), stamps=stamps,
            geo=geo,
        )

    def restricted(self, images, frames=None, part: str = "") -> Dataset:
        """The dataset with only the rows of `images` (ids) in images, image_lines and observations,
        and of `frames` (ids; default: the placements of those images that are flight images) in
        frames; the manifest and the points whole. Rows keep their order and index: these tables
        are the whole load's filtered. part: what the slice is (a job's, slices.py)."""
        chosen = self.images.iloc[self._rows("images", "image", images)]
        names = chosen["image"].to_numpy(dtype=object)
        if frames is None:
            frames = chosen.loc[chosen["stage"] == "flight", "placement"]
        return replace(self, images=chosen, frames=self.frames.iloc[self._rows("frames", "frame", frames)],
                       observations=self.observations.iloc[self._rows("observations", "image", names)],
                       image_lines={image: self.image_lines[image] for image in names}, part=part)

    def _rows(self, table: str, column: str, ids) -> np.ndarray:
        """Ascending positions of the rows of the `table` whose `column` is one of `ids`. Its rows are
        grouped by that column once, so that each of many slices costs only its own rows."""
        groups = self._positions.get((table, column))
        if groups is None:
            groups = self._positions[(table, column)] = getattr(self, table).groupby(column, sort=False).indices
        found = [groups[key] for key in pd.unique(np.asarray(ids, dtype=object).ravel()) if key in groups]
        return np.sort(np.concatenate(found)) if found else np.zeros(0, dtype=int)

    def check_image_files(self) -> None:
        """Each image's file still exists: the one check of the load that does not read a table (a
        slice's dataset runs it on its own images; a file that several images name is asked once)."""
        root, found = str(self.root), {}
        for image, path in zip(self.images["image"].to_numpy(object), self.images["path"].to_numpy(object)):
            if path and path not in found:
                found[path] = os.path.isfile(os.path.join(root, path))
            if path and not found[path]:
                raise self._image_error(image, _no_file(path))

    def __repr__(self) -> str:
        return f"Dataset({self.name!r}, root={str(self.root)!r})"

    @property
    def truth_dir(self) -> Path:
        """root / "truth": simulator ground truth, read only by evaluation and tests."""
        return self.root / TRUTH

    @property
    def points(self) -> pd.DataFrame:
        """Control and ground points in one frame indexed by point_id (columns x, y, z + extras)."""
        if self.ground_points.empty:
            return self.control_points.copy()
        return pd.concat([self.control_points, self.ground_points])

    def images_of(self, stage: str, camera: str | None = None, split: str | None = None) -> pd.DataFrame:
        """Rows of `images` of one stage, optionally of one camera and one split (copy, original index)."""
        if stage not in STAGES:
            raise ValueError(f"unknown stage {stage!r}; expected one of {STAGES}")
        keep = self.images["stage"] == stage
        if camera is not None:
            keep &= self.images["camera"] == camera
        if split is not None:
            keep &= self.images["split"] == split
        return self.images[keep].copy()

    def images_to_extract(self, stage: str | None = None) -> list[str]:
        """Images (of `stage`, if given) whose markers are extracted: with a file and no observations
        given in observations.csv."""
        images = self.images if stage is None else self.images_of(stage)
        given = set(self.observations["image"])
        return [image for image, path in zip(images["image"], images["path"]) if path and image not in given]

    def cameras_with_intrinsics_images(self) -> list[str]:
        """The cameras that have intrinsics images, in manifest order."""
        having = set(self.images_of("intrinsics")["camera"])
        return [camera for camera in self.cameras if camera in having]

    def image_path(self, image: str) -> Path | None:
        """Absolute path of `image`'s file, None when images.csv gives no path."""
        path = self._row(image)["path"]
        return self.root / path if path else None

    def read_image(self, image: str) -> np.ndarray:
        """(height, width) uint8 or uint16 grayscale pixels of `image`, checked against its camera's size."""
        row = self._row(image)
        if not row["path"]:
            raise self._image_error(image, "has no path (its observations are given in observations.csv)")
        return self._read_pixels(image, row["camera"], row["path"])

    def check_images(self) -> int:
        """Decode every image that has a path and check its size; returns how many were checked."""
        rows = self.images[self.images["path"] != ""]
        total = len(rows)
        for k, (image, camera, path) in enumerate(zip(rows["image"], rows["camera"], rows["path"]), 1):
            self._read_pixels(image, camera, path)
            if k % _PROGRESS_EVERY == 0 or k == total:
                log.info("checked %d/%d images", k, total)
        return total

    def summary(self) -> str:
        """A short multi-line description: cameras, points, images per stage and camera, frames, observations."""
        kinds: dict[CameraSpec, list[str]] = {}
        for name, spec in self.cameras.items():
            kinds.setdefault(spec, []).append(name)
        cameras = "; ".join(f"{', '.join(names)} {spec.width}x{spec.height}"
                            + (f" f={spec.focal_px:g}px" if spec.focal_px else "")
                            + (f" model {spec.model}" if spec.model != "radial1" else "") for spec, names in kinds.items())
        lines = [f"dataset {self.name} ({self.root})"]
        if self.description:
            lines.append(f"  {self.description}")
        lines += [
            f"cameras: {cameras} (reference {self.reference_camera})",
            f"points: {len(self.control_points)} control, {len(self.ground_points)} ground; "
            f"marker size {self.marker_size_m:g} m",
            f"images: {len(self.images)}, {int((self.images['path'] != '').sum())} with a file",
        ]
        if len(self.images):
            table = self.images.groupby(["stage", "camera"]).size().unstack(fill_value=0)
            table = table.reindex(index=[s for s in STAGES if s in table.index], columns=list(self.cameras),
                                  fill_value=0)
            lines += ["  " + line for line in table.rename_axis(index=None, columns=None).to_string().splitlines()]
        groups = self.frames["group"].nunique()
        lines.append(f"frames: {len(self.frames)} in {groups} group(s)")
        lines.append(f"observations: {len(self.observations)} on {self.observations['image'].nunique()} image(s)")
        return "\n".join(lines)

    # -------------------------------------------------------------- private

    def _row(self, image: str) -> pd.Series:
        """images.csv's row of `image`, found through `_rows`' groups (a mask per image would cost a
        batch of 100 images of a 50,055-image flight 100 passes over the whole table)."""
        rows = self._rows("images", "image", [image])
        if not len(rows):
            raise DatasetError(self.root / IMAGES, f"unknown image {image!r}")
        return self.images.iloc[rows[0]]

    def _image_error(self, image: str, message: str) -> DatasetError:
        return DatasetError(self.root / IMAGES, f"image {image!r}: {message}", self.image_lines.get(image))

    def _read_pixels(self, image: str, camera: str, path: str) -> np.ndarray:
        file = self.root / path
        if not file.is_file():
            raise self._image_error(image, _no_file(path))
        pixels, messages = _decode(file)
        if pixels is None or _CORRUPT.search(messages):
            said = f" ({'; '.join(messages.split(chr(10)))})" if messages else ""
            raise self._image_error(image, f"file {path!r} cannot be decoded{said}")
        if messages:
            log.debug("decoding %s: %s", file, messages)
        pixels = _grayscale(pixels)
        if pixels is None or pixels.dtype not in (np.uint8, np.uint16):
            raise self._image_error(image, f"file {path!r} is not an 8- or 16-bit grayscale, BGR or BGRA image")
        spec = self.cameras[camera]
        if pixels.shape != (spec.height, spec.width):
            raise self._image_error(image, f"file {path!r} is {pixels.shape[1]}x{pixels.shape[0]}, "
                                    f"camera {camera} expects {spec.width}x{spec.height}")
        return pixels


#: What libpng and libjpeg say of a file they could only partly decode (the rest would be grey).
_CORRUPT = re.compile(r"premature end|corrupt|truncat|incomplete|read error|crc error", re.IGNORECASE)


#: OpenCV's own log prefix, e.g. "[ WARN:0@3.384] global grfmt_png.cpp:793 readFromStreamOrBuffer ".
_OPENCV_LOG_PREFIX = re.compile(r"\[ ?\w+:[^\]]*\] (global )?\S+:\d+ \S+ ")


def _decode(file: Path) -> tuple[np.ndarray | None, str]:
    """The pixels of an image file (None when it cannot be decoded) and what the decoder libraries
    wrote to stderr meanwhile. libpng and libjpeg write warnings straight to file descriptor 2, so
    it is redirected while OpenCV decodes: a broken file gives one line of ours, not theirs too."""
    import cv2  # where images are read only: a job that reads none (pose) starts without OpenCV

    if file.stat().st_size == 0:
        return None, "empty file"
    saved = os.dup(2)
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 2)
        try:
            pixels = _read_file(cv2, file)
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        sink.seek(0)
        messages = sink.read().decode("utf-8", "replace").strip()
    return pixels, _OPENCV_LOG_PREFIX.sub("", messages)


def _read_file(cv2, file: Path) -> np.ndarray | None:
    """cv2.imread of `file` (unchanged: depth, channels, no EXIF turn): the decoder reads the file
    itself, where decoding its bytes from memory (cv2.imdecode) holds a copy of the whole file beside
    the pixels and, for an uncompressed TIFF, takes ~1.5 x as long. Its bytes are decoded instead
    where OpenCV cannot take the path as text (a file name of bytes that are not UTF-8), and where
    imread finds no image: it gives up on a truncated PNG without the decoder's complaint."""
    name = str(file)
    try:
        name.encode("utf-8")  # OpenCV's binding would crash the process on a name it cannot encode
        pixels = cv2.imread(name, cv2.IMREAD_UNCHANGED)
    except UnicodeEncodeError:
        pixels = None
    return pixels if pixels is not None else cv2.imdecode(np.frombuffer(file.read_bytes(), np.uint8),
                                                          cv2.IMREAD_UNCHANGED)


#: glibc's mallopt parameters (malloc.h) and the highest mmap threshold it takes (its 64-bit limit).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD, _HEAP_BLOCK_MAX = -1, -3, 32 * 2**20


def keep_freed_image_memory() -> bool:
    """Have the C allocator keep the memory of a freed image of up to 32 MB (a 16-bit 12 MP image) for
    the next one, in a process that reads images one after another (the markers and validate commands).
    By default glibc gives such a block a mapping of its own and hands it back when it is freed, so each
    image's pixels are faulted in and zeroed afresh: a page-cached 12 MP 16-bit TIFF then decodes in
    ~27 ms of which ~15 are those pages. Here blocks up to 32 MB come from the heap and its free top is
    kept (no trimming below 2 GB): the process keeps one image's memory, which it needed anyway. Larger
    images keep their mappings: glibc takes no higher threshold, and a 140 MP job with no mappings at
    all (M_MMAP_MAX 0) peaked at 3 x its image where it peaks at 2 x (fragments of the heap between
    images). Returns whether the allocator took the settings (False where the C library is not glibc)."""
    import ctypes

    try:
        mallopt = ctypes.CDLL(None).mallopt  # the process's own C library
    except (OSError, AttributeError):
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(_M_MMAP_THRESHOLD, _HEAP_BLOCK_MAX)) & bool(mallopt(_M_TRIM_THRESHOLD, 2**31 - 1))


def _grayscale(pixels: np.ndarray) -> np.ndarray | None:
    """(h, w) pixels from (h, w), (h, w, 1), BGR (h, w, 3) or BGRA (h, w, 4); None for other layouts."""
    import cv2

    if pixels.ndim == 3 and pixels.shape[2] == 1:
        return pixels[:, :, 0]
    if pixels.ndim == 3 and pixels.shape[2] in (3, 4):
        code = cv2.COLOR_BGR2GRAY if pixels.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        return cv2.cvtColor(pixels, code)
    return pixels if pixels.ndim == 2 else None


def _load_frames(root: Path, images: pd.DataFrame, image_table: Table, geo: Geo | None,
                 trajectory: tuple[str, str] | None = None) -> pd.DataFrame:
    """frames.csv (required when there are flight images); every flight placement must be a frame.
    With `geo`, the POS positions in the computation frame, and where a row gives its `time`
    instead, interpolated from the `trajectory` (path, format); INS attitudes given as angles
    (INS_ANGLES) or from the trajectory as prior_q* in the computation frame."""
    flight = (images["stage"] == "flight").to_numpy()
    if not (root / FRAMES).exists():
        if flight.any():
            line = image_table.lines[int(np.argmax(flight))]
            raise DatasetError(root / FRAMES, f"missing; {IMAGES} has flight images (first on line {line})")
        return _empty_frames()
    frames, table = _read_frames(root / FRAMES)
    if geo is not None:
        frames = _in_computation_frame(frames, FRAME_COLUMNS[2:], table, geo, pos=True)
    frames = _positions_and_attitudes(root, frames, table, geo, trajectory)
    placement = images["placement"].to_numpy(dtype=object)
    # pandas hashes the ids; np.isin on object arrays compares them pairwise (6 s for 50,000 images)
    unknown = flight & ~pd.Index(placement).isin(frames["frame"])
    image_table.check(unknown, lambda row: f"flight image {images['image'].iat[row]!r}: placement "
                      f"{placement[row]!r} is not a frame of {FRAMES}")
    return frames


def _check_sources(image_table: Table, images: pd.DataFrame, observed: np.ndarray) -> None:
    """Every image needs a file or observations in observations.csv (`observed`: the images they are on)."""
    names = images["image"].to_numpy(dtype=object)
    bad = (images["path"] == "").to_numpy() & ~pd.Index(names).isin(observed)
    image_table.check(bad, lambda row: f"image {names[row]!r} has neither a path nor rows in {OBSERVATIONS}")


# ------------------------------------------------------------------------------ writing and results


def write_dataset(
    root: str | Path,
    manifest: dict,
    control_points: pd.DataFrame,
    images: pd.DataFrame,
    *,
    ground_points: pd.DataFrame | None = None,
    frames: pd.DataFrame | None = None,
    observations: pd.DataFrame | None = None,
) -> Path:
    """Write the dataset files (not the image files) to `root` atomically; returns `root`.

    Frames are as `Dataset` holds them (points may also have point_id as a column; missing
    split/placement/path columns and None become ''). The manifest is validated first and written
    in canonical form. An optional file passed as None is not written and a stale copy is removed,
    so that the folder describes exactly what was passed. Floats are written with round-trip precision.
    """
    root = Path(root)
    parsed = _parse_manifest(manifest, root / MANIFEST)
    write_yaml_atomic(root / MANIFEST, _manifest_dict(parsed))
    write_csv_atomic(root / CONTROL_POINTS, _points_out(control_points))
    write_csv_atomic(root / IMAGES, _table_out(images, IMAGE_COLUMNS, (PRIOR_CENTER, PRIOR_QUAT), texts=IMAGE_COLUMNS))
    optional = {
        GROUND_POINTS: (ground_points, _points_out),
        FRAMES: (frames, lambda f: _table_out(f, FRAME_COLUMNS[:2], (FRAME_COLUMNS[2:], PRIOR_QUAT),
                                              texts=("frame", "group"))),
        OBSERVATIONS: (observations, lambda f: _table_out(f, OBSERVATION_COLUMNS, (), texts=("image", "point_id"))),
    }
    for name, (table, convert) in optional.items():
        if table is None:
            (root / name).unlink(missing_ok=True)
        else:
            write_csv_atomic(root / name, convert(table))
    return root


def _points_out(points: pd.DataFrame) -> pd.DataFrame:
    if "point_id" not in points.columns:
        points = points.rename_axis("point_id").reset_index()
    return _table_out(points, POINT_COLUMNS, ((POINT_SIGMA,), (POINT_SIGMA_Z,)), texts=("point_id",))


def _table_out(frame: pd.DataFrame, columns: Sequence[str], groups: Sequence[Sequence[str]],
               texts: Sequence[str]) -> pd.DataFrame:
    """`frame` with `columns` first, then each optional column group unless entirely absent/NaN, then extras."""
    out = frame.reset_index(drop=True).copy()
    for column in texts:
        values = out[column] if column in out else pd.Series([""] * len(out), dtype=object)
        out[column] = _strings([("" if _is_missing(value) else str(value)) for value in values])
    order = list(columns)
    for group in groups:
        present = [c for c in group if c in out]
        if present and out[present].notna().any().any():
            out = out.assign(**{c: np.nan for c in group if c not in out})
            order += list(group)
    known = set(columns).union(*groups) if groups else set(columns)
    order += [column for column in out.columns if column not in known]
    return out[order]


def _is_missing(value) -> bool:
    return value is None or (isinstance(value, float) and math.isnan(value))


def camera_of_images(images: pd.DataFrame) -> dict[str, str]:
    """{image: its camera} of an images table (Dataset.images)."""
    return dict(zip(images["image"].to_numpy(object), images["camera"].to_numpy(object)))


def read_observation_table(path: Path, dataset: Dataset) -> pd.DataFrame:
    """A results observations file (image, camera, point_id, u, v + extras) checked like the
    dataset's own: known images and points, the image's camera, inside the image, no repeats."""
    camera_of = camera_of_images(dataset.images)
    return _read_observations(path, camera_of, dataset.cameras, dataset.points.index, with_camera=True)[0]


def flight_observations(dataset: Dataset, observations: pd.DataFrame, cameras=None) -> pd.DataFrame:
    """The rows of `observations` (Workspace.load_observations) on flight images, of `cameras` if given,
    with a `frame` column: the image's placement in images.csv."""
    flight = dataset.images_of("flight")
    if cameras is not None:
        flight = flight[flight["camera"].isin(cameras)]
    frame_of = dict(zip(flight["image"], flight["placement"]))
    chosen = observations[observations["image"].isin(frame_of)].copy()
    chosen["frame"] = chosen["image"].map(frame_of)
    return chosen
