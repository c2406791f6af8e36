"""Writing results: atomic, and every failure to write or read is one line that leaves the earlier file."""

from __future__ import annotations

import errno
import os
import tempfile

import numpy as np
import pandas as pd
import pytest

from dmais_pipe import files
from dmais_pipe.files import csv_text
from dmais_pipe.cli import main
from dmais_pipe.errors import FileAccessError
from test_dataset import _inputs, _write


@pytest.fixture
def earlier(tmp_path):
    """A results folder holding a good table written earlier."""
    path = tmp_path / "results" / "tables" / "t.csv"
    files.write_csv_atomic(path, pd.DataFrame({"a": [1, 2]}))
    return path


def _leftovers(folder):
    return sorted(p.name for p in folder.iterdir() if p.name.endswith(".tmp"))


def test_disk_full_leaves_the_earlier_file_and_no_temporary(earlier, monkeypatch):
    before = earlier.read_bytes()
    real_fdopen = os.fdopen

    class FullDisk:
        def __init__(self, fd, mode):
            self.file = real_fdopen(fd, mode)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.file.close()

        def write(self, data):
            self.file.write(data[: len(data) // 2])
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(files.os, "fdopen", FullDisk)
    with pytest.raises(FileAccessError, match=rf"^{earlier}: No space left on device$"):
        files.write_csv_atomic(earlier, pd.DataFrame({"a": [3, 4, 5]}))
    assert earlier.read_bytes() == before and _leftovers(earlier.parent) == []


def test_a_file_where_a_folder_should_be(tmp_path):
    (tmp_path / "results").write_text("not a folder")
    with pytest.raises(FileAccessError, match=r"results/tables/t\.csv: "):
        files.write_text_atomic(tmp_path / "results" / "tables" / "t.csv", "x")
    assert (tmp_path / "results").read_text() == "not a folder"


@pytest.fixture
def dataset(tmp_path):
    return _write(tmp_path / "ds", _inputs())


def _one_line_error(capsys, *parts):
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    for part in parts:
        assert part in err, err


def test_cli_out_naming_a_regular_file_is_one_line(dataset, tmp_path, capsys):
    target = tmp_path / "afile"
    target.write_text("keep me")
    assert main(["summarize", str(dataset), "--out", str(target)]) == 2
    _one_line_error(capsys, "dmais summarize: error: ", str(target))
    assert target.read_text() == "keep me"


def test_cli_read_only_results_is_one_line_and_keeps_what_was_there(dataset, tmp_path, capsys, monkeypatch):
    """A read-only folder (simulated: the tests may run as root, whom permissions do not stop)."""
    reports = tmp_path / "reports"
    assert main(["summarize", str(dataset), "--out", str(reports)]) == 0
    capsys.readouterr()
    before = {p.name: p.read_bytes() for p in reports.iterdir()}

    def refuse(dir, **_):
        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), os.path.join(dir, ".x.tmp"))

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    assert main(["summarize", str(dataset), "--out", str(reports)]) == 2
    _one_line_error(capsys, "dmais summarize: error: ", str(reports), "Permission denied")
    assert {p.name: p.read_bytes() for p in reports.iterdir()} == before


def test_cli_unreadable_input_is_one_line(dataset, capsys, monkeypatch):
    real_open = open

    def guarded(path, *args, **kwargs):
        if str(path).endswith("dataset.yaml"):
            raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(path))
        return real_open(path, *args, **kwargs)

    monkeypatch.setattr("builtins.open", guarded)
    monkeypatch.setattr("pathlib.Path.read_text", lambda self, *a, **k: guarded(self).read())
    assert main(["validate", str(dataset)]) == 2
    _one_line_error(capsys, "dmais validate: error: ", "dataset.yaml: Permission denied")


def test_cli_never_writes_into_the_dataset_it_reads(dataset, tmp_path, capsys):
    """`--out` naming the dataset itself would have replaced its observations.csv with results."""
    before = {p: p.read_bytes() for p in dataset.rglob("*") if p.is_file()}
    assert main(["markers", str(dataset), "--out", str(dataset)]) == 2
    _one_line_error(capsys, "dmais markers: error: ", "lies in the dataset folder", "which dmais only reads")
    assert main(["summarize", str(dataset), "--out", str(dataset / "reports")]) == 2
    _one_line_error(capsys, "dmais summarize: error: ", "lies in the dataset folder")
    assert {p: p.read_bytes() for p in dataset.rglob("*") if p.is_file()} == before
    assert main(["summarize", str(dataset), "--out", str(tmp_path / "reports")]) == 0


def test_csv_text_writes_the_bytes_pandas_writes(monkeypatch):
    rng = np.random.default_rng(0)
    n = 400
    floats = rng.normal(size=n) * 10.0 ** rng.integers(-12, 14, n)
    floats[::7] = np.nan
    floats[3], floats[5], floats[8] = np.inf, 0.1, -0.0
    texts = np.array(["plain", "a,b", 'say "hi"', "two\nlines", "", "007", "cr\rhere"], dtype=object)[np.arange(n) % 7]
    frame = pd.DataFrame({"frame": texts, "x": floats, "n": rng.integers(-5, 10**12, n), "used": rng.random(n) < 0.5,
                          "mixed": np.array([1.5, None, "t", np.nan, True], dtype=object)[np.arange(n) % 5],
                          "a,b": texts[::-1]})
    frame["objects"] = pd.Series(texts, dtype=object)
    accented = frame.assign(**{"frame": frame["frame"] + "\u00e9", "h\u00f6he": 1.0})  # not ASCII: joined in Python
    frames = (frame, frame.iloc[:0], accented, frame.rename(columns={"x": "\u00f6"}))
    expected = [f.to_csv(index=False, lineterminator="\n") for f in frames]
    with monkeypatch.context() as patch:  # csv_text must build these itself
        patch.setattr(pd.DataFrame, "to_csv", None)
        assert [csv_text(f) for f in frames] == expected
    small = frame[["x"]].astype(np.float32).assign(y=1)  # float32: left to pandas
    assert csv_text(small) == small.to_csv(index=False, lineterminator="\n")
