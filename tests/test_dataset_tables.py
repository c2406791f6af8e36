"""dataset.py's CSV tables: the fast paths of reading, converting and checking a column against the
cell-by-cell ways they stand in for (seeded synthetic columns and files)."""

from __future__ import annotations

import codecs

import numpy as np
import pandas as pd
import pytest

from dmais_pipe import dataset
from dmais_pipe.dataset import Table, _parse_floats, _read_plain, _read_rows, _repeated, factorized, read_table
from dmais_pipe.errors import DatasetError


def _table(columns: dict, path="t.csv") -> Table:
    n = len(next(iter(columns.values())))
    return Table(path, {name: list(cells) for name, cells in columns.items()}, np.arange(2, n + 2))


def _float_cells(rng, n: int) -> list[str]:
    """Cells as files hold them: reprs of doubles of many magnitudes, short decimals, exponents, signs."""
    x = rng.normal(0, 1, n) * 10.0 ** rng.integers(-8, 12, n)
    cells = [repr(float(v)) for v in x]
    for k in rng.choice(n, n // 5, replace=False):
        cells[k] = rng.choice(["0", "-0.0", "1e5", "-2.5E-3", "+7", ".5", "5.", "1_000.5", "12345678901234567890",
                               "0.000001234", "4096"])
    return cells


def _reference_floats(cells: list[str], optional: bool) -> np.ndarray | DatasetError:
    """Table.floats as it was: numpy's conversion of the non-empty cells, else the first bad one's error."""
    text = np.array(cells, dtype=object)
    values = _parse_floats(text)
    bad = ~np.isfinite(values)
    if optional:
        bad &= text != ""
    if not bad.any():
        return values
    row = int(np.argmax(bad))
    message = f"column c: {text[row]!r} is not a finite number" if text[row] else "column c is empty; expected a number"
    return DatasetError("t.csv", message, row + 2)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("optional", [False, True])
def test_floats_of_a_column_are_the_cell_by_cell_ones_bit_for_bit(seed, optional):
    rng = np.random.default_rng(seed)
    cells = _float_cells(rng, 3000)
    columns = [cells]
    for bad in ("", "nan", "inf", "abc", "1.5.2", " ", "1e999"):
        damaged = list(cells)
        damaged[int(rng.integers(len(cells)))] = bad
        columns.append(damaged)
    for column in columns:
        expected = _reference_floats(column, optional)
        table = _table({"c": column})
        if isinstance(expected, DatasetError):
            with pytest.raises(DatasetError) as error:
                table.floats("c", optional)
            assert str(error.value) == str(expected)
        else:
            np.testing.assert_array_equal(table.floats("c", optional).view(np.int64), expected.view(np.int64))


def test_floats_of_an_absent_column_are_nan_or_an_error():
    table = _table({"a": ["1", "2"]})
    assert np.isnan(table.floats("b", optional=True)).all()
    with pytest.raises(DatasetError, match="column b is empty"):
        table.floats("b")


@pytest.mark.parametrize("kind", ["runs", "alternating", "mixed", "short", "one run"])
def test_factorized_column_is_pandas_factorize(kind):
    rng = np.random.default_rng(3)
    names = np.array([f"img_{k:05d}" for k in range(400)], dtype=object)
    if kind == "runs":  # every image's markers in a row, an image seen twice apart
        values = np.repeat(names[rng.integers(0, 400, 900)], rng.integers(1, 40, 900))
    elif kind == "alternating":
        values = names[rng.integers(0, 8, 5000)]
    elif kind == "mixed":
        values = np.concatenate([np.repeat(names[:50], 30), names[rng.integers(0, 400, 3000)]])
    elif kind == "short":
        values = names[rng.integers(0, 400, 700)]
    else:
        values = np.repeat(names[:1], 5000)
    values = np.array([str(v) for v in values], dtype=object)  # str objects of their own, as a file's split makes
    codes, distinct = factorized(values)
    expected_codes, expected_distinct = pd.factorize(values)
    np.testing.assert_array_equal(codes, expected_codes)
    assert list(distinct) == list(expected_distinct)


def test_repeated_keys_are_those_pandas_finds_duplicated():
    rng = np.random.default_rng(4)
    for trial in range(30):
        n = int(rng.integers(0, 300))
        columns = [rng.integers(0, int(rng.integers(1, 40)), n).astype(str).astype(object)
                   for _ in range(1 + trial % 3)]
        expected = pd.DataFrame({k: c for k, c in enumerate(columns)}).duplicated().any() if n else False
        assert _repeated([pd.factorize(c) for c in columns]) == expected


def test_check_unique_names_the_first_repeat_as_first_rows_does():
    table = _table({"image": ["a", "b", "a", "c", "b"], "point_id": ["1", "1", "2", "1", "1"]})
    with pytest.raises(DatasetError, match=r"line 6: duplicate observation \('b', '1'\) \(first on line 3\)"):
        table.check_unique(["image", "point_id"], "observation")
    _table({"image": ["a", "b", "a"], "point_id": ["1", "1", "2"]}).check_unique(["image", "point_id"], "observation")
    with pytest.raises(DatasetError, match=r"line 4: duplicate image id 'a' \(first on line 2\)"):
        _table({"image": ["a", "b", "a"]}).check_unique(["image"], "image id")


def test_required_text_finds_the_first_empty_cell_by_its_codes_too():
    table = _table({"image": ["a", "b", "", "a", ""]})
    for hashed in (False, True):
        if hashed:
            table.codes("image")
        with pytest.raises(DatasetError, match="line 4: column image is empty"):
            table.required_text("image")


def test_strings_are_new_objects_one_per_distinct_value_equal_to_the_cells():
    """No cell outlives its table through a column's strings (it would hold its neighbours' memory: Table.strings)."""
    rng = np.random.default_rng(8)
    cells = [f"P{k:05d}" for k in rng.integers(0, 300, 2000)] + ["", "é-1", "x y"]
    for hashed in (False, True):
        table = _table({"point_id": cells, "u": ["1.5"] * len(cells)})
        if hashed:
            table.codes("point_id")
        strings = table.strings("point_id")
        assert strings.tolist() == cells and str(strings.dtype) == "str"
        kept = {id(value) for value in strings.array.to_numpy(object)}
        assert len(kept) == len(set(cells))  # one object per value
        assert not kept & {id(cell) for cell in cells if len(cell) > 1}  # none of them a cell


def _plain_files(rng):
    """Plain CSV texts of a few shapes: blanks around cells, non-ASCII ids, no final line end, a BOM."""
    for trial in range(40):
        width, n = int(rng.integers(2, 6)), int(rng.integers(1, 60))
        header = [f"c{k}" for k in range(width)]
        rows = [[rng.choice(["", "a", " b ", "\tc", "é", "1.5", "x y", "\x1fz", "-3e-5"]) for _ in range(width)]
                for _ in range(n)]
        text = "\n".join(",".join(r) for r in [header] + rows) + ("\n" if trial % 3 else "")
        yield (codecs.BOM_UTF8 if trial % 7 == 0 else b"") + text.encode()


def test_plain_files_split_as_the_csv_module_reads_them(tmp_path):
    rng = np.random.default_rng(5)
    path = tmp_path / "t.csv"
    for data in _plain_files(rng):
        path.write_bytes(data)
        plain = _read_plain(path)
        header, rows, lines = _read_rows(path)
        assert plain is not None
        assert plain[0] == header
        assert [list(r) for r in zip(*plain[1])] == rows and lines == list(range(2, len(rows) + 2))


@pytest.mark.parametrize("text", ["a,b\n1,2,3\n", "a,b\n\n1,2\n", 'a,b\n"1",2\n', "a,b\r\n1,2\r\n", "a\n1\n",
                                  "a,b\n1,2\n3\n"])
def test_files_that_are_not_plain_are_left_to_the_csv_module(tmp_path, text):
    path = tmp_path / "t.csv"
    path.write_text(text, newline="")
    assert _read_plain(path) is None


def test_a_table_read_is_the_same_by_either_reader(tmp_path, monkeypatch):
    rng = np.random.default_rng(6)
    path = tmp_path / "t.csv"
    for data in _plain_files(rng):
        path.write_bytes(data)
        fast = read_table(path, ["c0"])
        with monkeypatch.context() as m:
            m.setattr(dataset, "_read_plain", lambda path: None)
            slow = read_table(path, ["c0"])
        pd.testing.assert_frame_equal(fast.cells, slow.cells)
        np.testing.assert_array_equal(fast.lines, slow.lines)
        for column in fast.columns:
            assert list(fast.text(column)) == list(slow.text(column))
            codes, distinct = fast.codes(column)
            assert list(distinct[codes]) == list(slow.text(column))
