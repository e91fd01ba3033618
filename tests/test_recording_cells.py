"""The signals CSV's cells: a value's repr, an empty cell for NaN or a column nobody filled;
frame-sourced columns filled from the frame they name only (hil/recording.py; the plant fills
them from the frames it receives, tests/test_house.py).

Invariant checked: equal rows give equal bytes (repr round-trips every float), and a missing
value is an empty cell, not "nan".
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from hil import cformat
from hil.errors import HilError
from hil.recording import SignalRecorder
from hil.rig import SignalSpec


def test_cells_and_frame_columns(tmp_path: Path) -> None:
    specs = [
        SignalSpec("kappa", "1/m", "true curvature", source="segment1.kappa"),
        SignalSpec("kappa_ref", "1/m", "reference", frame=("ControllerState", 1, "kappa_ref")),
        SignalSpec("kappa_est", "1/m", "estimate", frame=("ControllerState", 1, "kappa_est")),
        SignalSpec("fault", "", "fault bits", source="drive1.fault"),
        SignalSpec("kappa_ref2", "1/m", "reference 2", frame=("ControllerState", 2, "kappa_ref")),
    ]
    recorder = SignalRecorder(tmp_path / "signals.csv", specs)
    assert recorder.frame_columns("ControllerState", 1) == [
        ("kappa_ref", "kappa_ref"),
        ("kappa_est", "kappa_est"),
    ]
    assert recorder.frame_columns("ControllerState", 2) == [("kappa_ref", "kappa_ref2")]
    assert recorder.frame_columns("ControllerState", 3) == []
    assert recorder.frame_columns("DriveStatus", 1) == []
    assert recorder.source_columns == ["kappa", "fault"]
    recorder.set_cells([("kappa_ref", 9.0)])  # no open row: nothing to fill
    recorder.begin_row(0.01, (0.1 + 0.2, 3))
    # kappa_est is not given
    recorder.set_cells([("kappa_ref2", 4.0)])
    recorder.set_cells([("kappa_ref", -2.5)])
    recorder.set_cells([("kappa", 7.0)])  # a sourced column takes the plant's value
    recorder.begin_row(0.02, (math.nan, 0))  # ends the first row
    with pytest.raises(HilError, match="signals.csv: a row of 1 values for 2 sourced columns"):
        recorder.begin_row(0.03, (1.0,))
    recorder.close()
    lines = (tmp_path / "signals.csv").read_text().splitlines()
    assert lines == [
        "time,kappa,kappa_ref,kappa_est,fault,kappa_ref2",
        "0.01,0.30000000000000004,-2.5,,3,4.0",
        "0.02,,,,0,",
    ]


@pytest.mark.parametrize("writer", ["c", "python"])
def test_rows_are_what_the_csv_writer_writes_for_any_numbers(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, writer: str
) -> None:
    """Rows of plain numbers take a quicker path than csv.writer (C, hil.cformat, or repr
    joined); whatever the values (ints, floats of every magnitude, -0.0, inf, NaN, bools,
    numpy scalars), the file is the same."""
    import csv
    import io

    import numpy as np

    rng = np.random.default_rng(5)
    if writer == "python":
        monkeypatch.setattr(cformat, "load", lambda: None)
    elif cformat.load() is None:
        pytest.skip(f"no C formatter here: {cformat.failure()}")
    specs = [SignalSpec(f"s{i}", "", "", source=f"p.s{i}") for i in range(4)]
    recorder = SignalRecorder(tmp_path / "signals.csv", specs)
    assert (recorder._format_row is None) == (writer == "python")
    written_in_c: list[str | None] = []
    if recorder._format_row is not None:  # count the rows C wrote (the plain ones, most)
        c_row = recorder._format_row

        def counted(values: list[float]) -> str | None:
            written_in_c.append(c_row(values))
            return written_in_c[-1]

        recorder._format_row = counted
    expected = io.StringIO()
    reference = csv.writer(expected, lineterminator="\n")
    reference.writerow(["time", *(s.column for s in specs)])
    # the csv writer quotes a cell with a comma or a quote in it (a tuple's repr, a string's)
    odd = [math.inf, -math.inf, math.nan, True, np.float64(0.5), -0.0, 10**20, 1e-300, 7]
    odd += [(1.0, 2.0), 'say "a,b"']
    for k in range(300):
        values = [float(v) for v in rng.normal(0.0, 10.0 ** rng.integers(-8, 8), 4)]
        if k % 3 == 0:
            values[k % 4] = odd[(k // 3) % len(odd)]
        recorder.begin_row(k * 0.01, values)
        row = [k * 0.01, *values]
        reference.writerow(["" if isinstance(v, float) and v != v else repr(v) for v in row])
    recorder.close()
    assert (tmp_path / "signals.csv").read_text() == expected.getvalue()
    if writer == "c":
        assert sum(line is not None for line in written_in_c) > 200


def test_the_plant_records_a_frames_signals_only(tmp_path: Path) -> None:
    """A received frame fills the columns of its own DBC signals: a column that names a field
    which is not one (the index, carried by the CAN id) or a signal of another frame stays
    empty, and a frame with no recorded signal is not recorded."""
    from types import SimpleNamespace

    from hil.plant import Plant
    from rigbus.protocol import ControllerState

    specs = [
        SignalSpec("kappa_ref", "1/m", "reference", frame=("ControllerState", 1, "kappa_ref")),
        SignalSpec("node", "", "not a signal", frame=("ControllerState", 1, "node")),
        SignalSpec("kappa_ref2", "1/m", "reference 2", frame=("ControllerState", 2, "kappa_ref")),
    ]
    recorder = SignalRecorder(tmp_path / "signals.csv", specs)
    plant = SimpleNamespace(nodes=[], signals=recorder)
    route = Plant._route(plant, ControllerState(1, 2.5, 0.5, 7))  # type: ignore[arg-type]
    assert route.recorded == (("kappa_ref", "kappa_ref"),) and route.nodes == ()
    assert Plant._route(plant, ControllerState(3, 2.5, 0.5, 7)).recorded == ()  # type: ignore[arg-type]
    recorder.close()
