"""repr of floats in C (hil/cformat.py, hil/_cformat.c): the signals CSV's rows.

Invariant checked: `float_repr(x) == repr(x)` for every double tried (random bit patterns of
every exponent, subnormals, powers of two, powers of ten, decimals of 1-17 digits, the halfway
and boundary cases), and `format_row` writes what csv.writer writes for the texts the recorder
gives it, or declines (None) the rows it does not write.
"""

from __future__ import annotations

import csv
import io
import math
import random
import shutil
import struct
import sys

import pytest

from hil import cformat

module = cformat.load()
needs_c = pytest.mark.skipif(module is None, reason=f"no C formatter here: {cformat.failure()}")


def test_the_module_builds_where_gcc_and_the_headers_are() -> None:
    if shutil.which("gcc") is None or cformat.failure() == f"{cformat.ENV}=python":
        pytest.skip("no gcc, or SOFTHIL_FORMAT=python")
    assert module is not None, cformat.failure()


def _doubles(count: int, seed: int) -> list[float]:
    rnd = random.Random(seed)
    values = []
    while len(values) < count:
        x = struct.unpack("<d", rnd.getrandbits(64).to_bytes(8, "little"))[0]
        if x == x:
            values.append(x)
    return values


def _edges() -> list[float]:
    values = [0.0, -0.0, math.inf, -math.inf, 5e-324, -5e-324, sys.float_info.min]
    values += [sys.float_info.max, sys.float_info.epsilon, 2.2250738585072009e-308]
    values += [2.0**e for e in range(-1074, 1024)]  # every power of two: asymmetric intervals
    values += [float(10**k) for k in range(309)] + [float(f"1e-{k}") for k in range(1, 324)]
    # where repr turns from fixed to exponent notation, and back
    values += [1e16, 9999999999999998.0, 1e15, 123456789012345678.0, 1e-4, 9.999999999999999e-5]
    values += [0.1, 0.2, 0.3, 1 / 3, 2 / 3, 0.025, 0.024999999999999998, 1e22, 1e23, 5e-310]
    values += [math.nextafter(v, math.inf) for v in list(values) if math.isfinite(v)]
    return values + [-v for v in values]


@needs_c
def test_float_repr_is_repr() -> None:
    assert module is not None
    rnd = random.Random(3)
    decimals = [
        round(rnd.uniform(-1000.0, 1000.0), rnd.randint(0, 17)) * 10.0 ** rnd.randint(-30, 30)
        for _ in range(100_000)
    ]
    for values in (_edges(), _doubles(300_000, 11), decimals):
        wrong = [x for x in values if module.float_repr(x) != repr(x)]
        assert wrong == [], [(repr(x), module.float_repr(x)) for x in wrong[:5]]
    assert module.float_repr(math.nan) == "nan"


def _csv_line(row: list[object]) -> str:
    out = io.StringIO()
    csv.writer(out, lineterminator="\n").writerow(
        ["" if isinstance(v, float) and v != v else repr(v) for v in row]
    )
    return out.getvalue()


@needs_c
def test_rows_are_what_csv_writes() -> None:
    assert module is not None
    rows: list[list[object]] = [
        [0.0, 1.5, -0.0, math.nan, math.inf, -math.inf, 7, -(10**30), 0],
        [math.nan, math.nan],
        [1.0],
        [3],
        _doubles(67, 5),
        _doubles(400, 6),  # longer than the stack buffer: written from the heap
        [10**400, 2.5],  # an int with more digits than a float has
    ]
    for row in rows:
        assert module.format_row(row) == _csv_line(row), row


@needs_c
@pytest.mark.parametrize(
    "row",
    [[1.0, True], [1.0, "a"], [None, 2.0], [1.0, (1.0, 2.0)], [math.nan], [1.0, 2.0j]],
    ids=["bool", "str", "None", "tuple", "one NaN cell", "complex"],
)
def test_rows_it_does_not_write_are_declined(row: list[object]) -> None:
    """Another type than float or int (a subclass too: bool, numpy's float64), or a row of one
    NaN cell (which csv.writer writes as a quoted empty string): None, and Python writes it."""
    import numpy as np

    assert module is not None
    assert module.format_row(row) is None
    assert module.format_row([1.0, np.float64(0.5)]) is None
    with pytest.raises(TypeError):
        module.format_row((1.0, 2.0))


def test_tables_are_ryus() -> None:
    """The first entries of Ryu's published tables (ryu/d2s_full_table.h)."""
    text = cformat.tables()
    assert "{1u, 2305843009213693952u},\n{11068046444225730970u, 1844674407370955161u}" in text
    assert "{0u, 1152921504606846976u},\n{0u, 1441151880758558720u}" in text


def test_python_only_and_a_misspelt_setting(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(cformat._part, "value", None)
    monkeypatch.setattr(cformat._part, "failure", None)
    monkeypatch.setenv(cformat.ENV, "python")
    assert cformat.load() is None and cformat.failure() == "SOFTHIL_FORMAT=python"
    monkeypatch.setattr(cformat._part, "failure", None)
    monkeypatch.setenv(cformat.ENV, "pyhton")
    with pytest.raises(ValueError, match="^SOFTHIL_FORMAT='pyhton': must be c .* or python$"):
        cformat.load()
    from hil.cli import main as hil_main

    assert hil_main(["scenarios"]) == 1
