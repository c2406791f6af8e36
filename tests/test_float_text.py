"""The compiled float64 cells (`_float_text.float_cells`): each exactly Python's repr, NaN empty, over
more than a million seeded doubles drawn many ways (bit patterns of every exponent, decimals, integers,
powers of two and their neighbours, halves, the ends of the round-trip interval); and `files.csv_text`
with them, the bytes pandas' to_csv writes. The reading (`_float_text.cells_floats`): float()'s bits of
those cells, of long and tie-like decimals and of every form float() accepts or refuses."""

from decimal import Decimal


import numpy as np
import pandas as pd
import pytest

from dmais_pipe._float_text import cells_floats, float_cells
from dmais_pipe.files import csv_text


def _reprs(x: np.ndarray) -> list[str]:
    return ["" if value != value else repr(value) for value in x.tolist()]


def _bits(rng, n: int, low: int, high: int, fraction_bits: int = 52) -> np.ndarray:
    """(n,) doubles of random sign, biased exponent in [low, high) and fraction_bits random leading
    fraction bits (the others 0: short binary fractions, whose decimals are short or tie-like)."""
    exponent = rng.integers(low, high, n, dtype=np.uint64) << np.uint64(52)
    fraction = rng.integers(0, 2**52, n, dtype=np.uint64) >> np.uint64(52 - fraction_bits) << np.uint64(52 - fraction_bits)
    sign = rng.integers(0, 2, n, dtype=np.uint64) << np.uint64(63)
    return (sign | exponent | fraction).view(np.float64)


def _draws(seed: int) -> dict[str, np.ndarray]:
    """Doubles drawn several ways, ~1.1 million in all."""
    rng = np.random.default_rng(seed)
    powers = 2.0 ** np.arange(-1074, 1024)
    return {
        "any bit pattern": rng.integers(0, 2**64, 200_000, dtype=np.uint64).view(np.float64),
        "subnormal, zero": _bits(rng, 20_000, 0, 1),
        "the fast exponents": _bits(rng, 200_000, 1023 - 60, 1023 + 60),
        "few fraction bits": np.concatenate([_bits(rng, 20_000, 1023 - 60, 1023 + 60, k) for k in (1, 2, 4, 8, 16)]),
        "normal 1e-15..1e20": rng.normal(size=150_000) * 10.0 ** rng.uniform(-15, 20, 150_000),
        "uniform 1e-15..1e20": rng.uniform(0, 10, 100_000) * 10.0 ** rng.integers(-16, 20, 100_000),
        "0..10 decimals": np.concatenate([np.round(rng.normal(size=15_000) * 10.0 ** rng.integers(-3, 9, 15_000), k)
                                          for k in range(11)]),
        "integers": np.concatenate([rng.integers(-10**k, 10**k, 10_000).astype(float) for k in range(1, 19)]),
        "short decimals": rng.integers(1, 10**6, 100_000) * 10.0 ** rng.integers(-20, 22, 100_000),
        "powers of two, neighbours": np.concatenate([powers, np.nextafter(powers, 0), np.nextafter(powers, np.inf),
                                                     -powers]),
        "halves": (rng.integers(-10**9, 10**9, 50_000) + 0.5) / 2.0 ** rng.integers(0, 30, 50_000),
        "special": np.array([0.0, -0.0, np.inf, -np.inf, np.nan, -np.nan, 5e-324, 2.2250738585072014e-308,
                             1.7976931348623157e308, 0.1, 0.3, 2 / 3, 1e-05, 1.5e-07, 0.0001, 1e16, 1e15,
                             9999999999999998.0, 1.2345678901234568e+17, 1234567.0, 0.001, -0.5, 123.0,
                             2.0**-49, 2.0**55, np.nextafter(2.0**-49, 0), np.nextafter(2.0**55, 0)]),
    }


@pytest.mark.parametrize("seed", [0])
def test_cells_are_repr_byte_for_byte(seed):
    draws = _draws(seed)
    assert sum(map(len, draws.values())) > 1_000_000
    for name, x in draws.items():
        cells = float_cells(x)
        assert all(type(cell) is str for cell in cells), name
        bad = [(value, cell) for value, cell, expected in zip(x.tolist(), cells, _reprs(x)) if cell != expected]
        assert not bad, (name, bad[:5])


def test_the_interval_ends_read_back_where_the_significand_is_even():
    """Above 2**54 the doubles are 4 apart and the midpoint x + 2 or x - 2 can end in 0: it is one of x's
    decimals (one digit fewer) only where x's significand is even (reading rounds half to even)."""
    x = 2.0**54 + 4.0 * np.arange(1_000)
    ends = x[((x + 2) % 10 == 0) | ((x - 2) % 10 == 0)]
    assert min(np.sum(ends / 4 % 2 == 0), np.sum(ends / 4 % 2 == 1)) >= 100  # x = 4 m
    assert float_cells(ends) == _reprs(ends)
    assert float_cells(np.array([18014398509481992.0, 18014398509481988.0])) == \
        ["1.801439850948199e+16", "1.8014398509481988e+16"]


def test_layout_is_reprs():
    x = np.array([1e-05, 1.5e-07, 0.0001, 1e16, 1e15, 1234567.0, 0.001, -0.5, 1.2345678901234568e+17,
                  -1.5e-300, 12.0, 0.1])
    assert float_cells(x) == ["1e-05", "1.5e-07", "0.0001", "1e+16", "1000000000000000.0", "1234567.0", "0.001",
                              "-0.5", "1.2345678901234568e+17", "-1.5e-300", "12.0", "0.1"]


def test_any_float64_array():
    x = np.arange(12.0).reshape(3, 4) / 7
    assert float_cells(x[:, 1]) == _reprs(x[:, 1])  # strided
    assert float_cells(np.array([], dtype=np.float64)) == []
    assert float_cells([0.5, np.nan]) == ["0.5", ""]


def test_csv_text_with_float_cells_is_pandas_to_csv():
    rng = np.random.default_rng(1)
    n = 20_000
    values = np.concatenate([rng.normal(0, 1000, n // 4), np.round(rng.uniform(0, 4000, n // 4), 3),
                             rng.normal(size=n // 4) * 10.0 ** rng.integers(-20, 22, n // 4),
                             rng.integers(-10**6, 10**6, n // 4).astype(float)])
    values[::13] = np.nan
    values[5::97] = np.inf
    frame = pd.DataFrame({"frame": [f"g1_f{i:04d}" for i in range(n)], "u": values, "v": rng.permutation(values),
                          "used": rng.random(n) < 0.9, "n": rng.integers(-5, 10**12, n),
                          "var_x_m2": rng.uniform(1e-9, 1e-3, n) ** 2, "note": np.where(np.arange(n) % 9, "a,b", "")})
    frame["frame"] = frame["frame"].astype("string")
    assert csv_text(frame) == frame.to_csv(index=False, lineterminator="\n")


def _floats(cells: list[str]) -> np.ndarray | None:
    """The reference: float() of each cell, None where one raises."""
    try:
        return np.array([float(cell) for cell in cells], dtype=float)
    except ValueError:
        return None


def _same_bits(a: np.ndarray, b: np.ndarray) -> bool:
    return a.shape == b.shape and bool((a.view(np.uint64) == b.view(np.uint64)).all())


def _midpoints(rng, n: int) -> list[str]:
    """Exact decimals of the midpoints between neighbouring doubles (where reading must round half to even),
    and of numbers just beside them (a digit more or less at the 40th place)."""
    x = np.abs(_bits(rng, n, 1, 2046))
    x = x[np.isfinite(x) & (x > 0)]
    cells = []
    for value, nudge in zip(x.tolist(), rng.integers(-1, 2, len(x)).tolist()):
        middle = (Decimal(value) + Decimal(np.nextafter(value, np.inf))) / 2
        cells.append(f"{middle + nudge * middle.scaleb(-40):.60e}" if nudge else f"{middle:.60e}")
    return cells


def test_reading_gives_floats_bits():
    rng = np.random.default_rng(1)
    for name, x in _draws(1).items():
        cells = [cell for cell in _reprs(x) if cell]
        assert _same_bits(cells_floats(cells, len(cells)), _floats(cells)), name
    digits = rng.integers(0, 10, (60_000, 40)).astype(str)
    lengths, exponents = rng.integers(1, 41, 60_000), rng.integers(-360, 330, 60_000)
    decimals = [("-" if k % 3 == 0 else "") + "".join(row[:m - 1]) + "." + row[m - 1] + f"e{e:+d}"
                for k, (row, m, e) in enumerate(zip(digits, lengths, exponents))]
    for name, cells in {"long decimals": decimals, "midpoints": _midpoints(rng, 20_000),
                        "forms": ["1", "-0", "+0.0", ".5", "5.", "007", "1E5", "1e-400", "1e400", "-1e400",
                                  "4.9e-324", "2.4703282292062328e-324", "2.4703282292062327e-324",
                                  "1.7976931348623158e308", "1.7976931348623159e308", "nan", "-inf", "Infinity",
                                  " 3 ", "1_000.5", "\u0663.5", "0" * 400 + "1", "1" + "0" * 400]}.items():
        assert _same_bits(cells_floats(cells, len(cells)), _floats(cells)), name
    assert cells_floats((cell for cell in ["1.5", "2"]), 2).tolist() == [1.5, 2.0]  # any iterable


@pytest.mark.parametrize("cell", ["", "1e", "e5", ".", "-", "+-1", "1.2.3", "1e+", "0x1p3", "abc", "1 2", "nan5",
                                  "1__0", "--1", "1e5e5"])
def test_reading_refuses_what_float_refuses(cell):
    with pytest.raises(ValueError):
        float(cell)
    assert cells_floats(["1.0", cell], 2) is None


def test_reading_checks_the_count():
    with pytest.raises(ValueError, match="3 cells, expected 2"):
        cells_floats(["1", "2", "3"], 2)
