"""Atomic writing of results: a temporary file in the target's folder, then a rename.

A failed run therefore never leaves a half-written file under a name that looks complete, and a
write that fails (permission, a file where a folder should be, disk full) leaves the earlier file
as it was and raises a FileAccessError naming the target.
"""

from __future__ import annotations

import json
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pandas as pd
import yaml

from ._float_text import csv_lines, float_cells
from .errors import FileAccessError

_UMASK = os.umask(0)
os.umask(_UMASK)

#: Folders nothing may be written into: the datasets a `dmais` command reads (`read_only`).
_READ_ONLY: list[Path] = []


@contextmanager
def read_only(folder: str | Path | None):
    """Within the block, refuse every write into `folder` (and below): a command's dataset is only
    read, whatever --out, --csv or --html name. None protects nothing."""
    if folder is None:
        yield
        return
    _READ_ONLY.append(Path(folder).resolve())
    try:
        yield
    finally:
        _READ_ONLY.pop()


def _check_writable(path: Path) -> None:
    target = path.resolve()
    for folder in _READ_ONLY:
        if target == folder or folder in target.parents:
            raise FileAccessError(path, f"lies in the dataset folder {folder}, which dmais only reads; "
                                  "write results elsewhere")


def write_bytes_atomic(path: str | Path, data: bytes) -> Path:
    """Write `data` to `path` through a temporary file and a rename; creates parent folders."""
    path = Path(path)
    _check_writable(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except FileExistsError:  # mkdir: a file stands where a folder of the path should be
        raise FileAccessError(path, "a file stands where a folder of this path should be") from None
    except OSError as error:
        raise FileAccessError.of(error, path) from None
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600; give the file the usual permissions
        os.replace(tmp, path)
    except OSError as error:
        Path(tmp).unlink(missing_ok=True)
        raise FileAccessError.of(error, path) from None
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def copy_atomic(source: str | Path, target: str | Path) -> Path:
    """Copy the file `source` to `target` atomically."""
    return write_bytes_atomic(target, Path(source).read_bytes())


def write_text_atomic(path: str | Path, text: str) -> Path:
    return write_bytes_atomic(path, text.encode("utf-8"))


def write_json_atomic(path: str | Path, data) -> Path:
    return write_text_atomic(path, json.dumps(data, indent=2) + "\n")


def write_yaml_atomic(path: str | Path, data) -> Path:
    return write_text_atomic(path, yaml.safe_dump(data, sort_keys=False))


def write_csv_atomic(path: str | Path, frame: pd.DataFrame, float_format: str | None = None) -> Path:
    return write_text_atomic(path, frame.to_csv(index=False, float_format=float_format, lineterminator="\n"))


#: Column types `csv_text` writes itself, besides text (others go through pandas).
_PLAIN_DTYPES = (np.dtype(float), np.dtype(np.int64), np.dtype(bool), np.dtype(object))


def csv_text(frame: pd.DataFrame) -> str:
    """`frame.to_csv(index=False, lineterminator="\\n")`'s text, built column by column: the same bytes
    (floats as their shortest repr, NaN and None empty, bools True/False, fields quoted only where
    they hold a comma, a quote or a "\\n") several times faster for large tables, the float64 cells by
    the compiled `_float_text.float_cells`, the lines by `_float_text.csv_lines` where every cell is ASCII."""
    if frame.shape[1] < 2 or not all(d in _PLAIN_DTYPES or isinstance(d, pd.StringDtype) for d in frame.dtypes):
        return frame.to_csv(index=False, lineterminator="\n")
    columns = [_csv_cells(frame[name]) for name in frame.columns]
    header = ",".join(_csv_quoted([str(name) for name in frame.columns]))
    text = csv_lines(header, columns)
    return text if text is not None else "\n".join([header, *map(",".join, zip(*columns))]) + "\n"


def _csv_cells(column: pd.Series) -> list[str]:
    """A column's cells as CSV fields (see `csv_text`)."""
    if column.dtype == np.float64:
        return float_cells(column.to_numpy())
    if column.dtype.kind in "iub":
        return list(map(str, column.tolist()))
    if isinstance(column.dtype, pd.StringDtype) and not column.isna().any():
        return _csv_quoted(column.tolist())  # every cell a str already
    return _csv_quoted([value if isinstance(value, str) else "" if pd.isna(value) else str(value)
                        for value in column.tolist()])


def _csv_quoted(cells: list[str]) -> list[str]:
    special = ('"', ",", "\n")  # as the csv module with lineterminator "\\n"
    joined = "\0".join(cells)
    if not any(c in joined for c in special):
        return cells
    return [f'"{cell.replace(chr(34), chr(34) * 2)}"' if any(c in cell for c in special) else cell for cell in cells]


def write_png_atomic(path: str | Path, image: np.ndarray, compression: int = 1) -> Path:
    """Write an 8- or 16-bit grayscale image as PNG (compression 0-9, low is fast)."""
    import cv2  # OpenCV for the few that write images, not for every command

    ok, encoded = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, int(compression)])
    if not ok:
        raise OSError(f"could not encode {path} as PNG")
    return write_bytes_atomic(path, encoded.tobytes())
