"""The signals' cells: kept in column blocks (Parquet files written as the run goes), the CSV
made from them at close or by `hil csv` after a kill: a value's repr, an empty cell for NaN or a
column nobody filled; frame-sourced columns filled from the frame they name only
(hil/recording.py, hil/blocks.py; the plant fills them from the frames it receives,
tests/test_house.py).

Invariant checked: equal rows give equal bytes (repr round-trips every float), a missing value
is an empty cell, not "nan", and the blocks on disk are whole and in order.
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path

import numpy as np
import pytest

from hil import blocks, recording
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


def _reference_line(row: list[object]) -> str:
    """A row as the CSV had it before the blocks: csv.writer on each value's repr, a NaN float
    an empty cell; numpy's numbers as the float or int they are (the C formatter wrote a numpy
    float so; a numpy integer was "np.int64(3)", now "3")."""
    out = io.StringIO()
    cells = []
    for v in row:
        if isinstance(v, float):
            cells.append("" if v != v else repr(float(v)))
        elif isinstance(v, np.integer):
            cells.append(repr(int(v)))
        else:
            cells.append(repr(v))
    csv.writer(out, lineterminator="\n").writerow(cells)
    return out.getvalue()


def test_rows_are_what_the_csv_writer_writes_for_any_numbers(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Whatever the numbers (floats of every magnitude, subnormal, -0.0, inf, NaN, ints, bools,
    numpy floats), in blocks of every size, the CSV made from the blocks is csv.writer's on
    their reprs: the shortest text that reads back as the float, an integer as an integer."""
    rng = np.random.default_rng(5)
    specs = [SignalSpec(f"s{i}", "", "", source=f"p.s{i}") for i in range(4)]
    clock = iter(range(10**6))
    monkeypatch.setattr(recording.time, "monotonic", lambda: next(clock) * 0.1)  # a block: 3 rows
    recorder = SignalRecorder(tmp_path / "signals.csv", specs)
    expected = ["time,s0,s1,s2,s3\n"]
    odd = [math.inf, -math.inf, math.nan, True, False, np.float64(0.5), -0.0, 2**53, -7]
    odd += [5e-324, 1e-300, 1e16, 1e22, 123456789012345680.0, 0.1 + 0.2, np.int64(3), 0]
    for k in range(300):
        values: list[object] = [float(v) for v in rng.normal(0.0, 10.0 ** rng.integers(-8, 8), 4)]
        if k % 3 == 0:
            values[k % 4] = odd[(k // 3) % len(odd)]
        if k % 50 == 7:
            values = [math.nan] * 4
        recorder.begin_row(k * 0.01, values)  # type: ignore[arg-type]
        expected.append(_reference_line([k * 0.01, *values]))
    recorder.close()
    assert (tmp_path / "signals.csv").read_text() == "".join(expected)
    parts = sorted((tmp_path / "signals.parquet").iterdir())
    assert len(parts) == 100 and parts[0].name == "part-000000.parquet"


@pytest.mark.parametrize("value", ["1.5", (1.0, 2.0), None, 2**53 + 1, complex(1, 1)])
def test_a_cell_that_is_not_a_number_fails_the_run_with_its_column(
    tmp_path: Path, value: object
) -> None:
    """A cell must be a number a float64 column holds (an integer up to 2^53 exactly): else a
    HilError naming the column and row; the CSV keeps the blocks written before."""
    specs = [SignalSpec("kappa", "1/m", "", source="p.k"), SignalSpec("x", "", "", source="p.x")]
    recorder = SignalRecorder(tmp_path / "signals.csv", specs)
    recorder.begin_row(0.0, (1.0, 2.0))
    recorder.end_row()
    recorder._write_block()
    recorder.begin_row(0.01, (1.0, value))  # type: ignore[arg-type]
    recorder.end_row()
    with pytest.raises(HilError, match=r"signal 'x', row 2: .* (not a number|beyond 2\^53)"):
        recorder._write_block()
    recorder.close()  # quietly, after the failure: the CSV of the block before it
    assert (tmp_path / "signals.csv").read_text() == "time,kappa,x\n0.0,1.0,2.0\n"


def test_the_blocks_are_written_as_the_run_goes_and_a_killed_runs_csv_is_made_from_them(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Every FLUSH_INTERVAL of wall time the rows so far are a block on disk; a recorder never
    closed (a run killed hard) leaves them, and `write_csv` makes the CSV of their rows: the
    first lines of the CSV the closed recorder writes, byte for byte. A temporary file that a
    kill left (a block cut short) is not a block."""
    now = [0.0]
    monkeypatch.setattr(recording.time, "monotonic", lambda: now[0])
    specs = [SignalSpec("kappa", "1/m", "curvature", source="p.k")]
    specs.append(SignalSpec("phase", "", "phase", frame=("ControllerState", 1, "phase")))
    folders = []
    for name in ("killed", "closed"):
        folder = tmp_path / name
        folder.mkdir()
        recorder = SignalRecorder(folder / "signals.csv", specs)
        for k in range(10):
            recorder.begin_row(k * 0.01, (k / 3,))
            recorder.set_cells([("phase", k // 4)])
            now[0] += 0.1  # a block every third row
        folders.append(folder)
        if name == "closed":
            recorder.close()
    killed, closed = folders
    assert not (killed / "signals.csv").exists()
    assert sorted(p.name for p in (killed / "signals.parquet").iterdir()) == [
        "part-000000.parquet",
        "part-000001.parquet",
        "part-000002.parquet",
    ]
    (killed / "signals.parquet" / ".part-000003.parquet.partial").write_bytes(b"PAR1 cut")
    assert blocks.write_csv(killed / "signals.csv") == 9
    lines = (closed / "signals.csv").read_text().splitlines(keepends=True)
    assert len(lines) == 11 and lines[4] == "0.03,1.0,0\n" and lines[10] == "0.09,3.0,2\n"
    assert (killed / "signals.csv").read_text() == "".join(lines[:10])


def test_blocks_that_do_not_follow_are_refused(tmp_path: Path) -> None:
    """A block missing in the middle, or another run's, is an error naming it, not a CSV with
    a gap."""
    specs = [SignalSpec("kappa", "1/m", "", source="p.k")]
    recorder = SignalRecorder(tmp_path / "signals.csv", specs)
    for k in range(3):
        recorder.begin_row(k * 0.01, (1.0,))
        recorder.end_row()
        recorder._write_block()
    recorder._closed = True  # killed
    folder = tmp_path / "signals.parquet"
    (folder / "part-000001.parquet").unlink()
    with pytest.raises(HilError, match="part-000002.parquet: does not follow block 0"):
        blocks.write_csv(tmp_path / "signals.csv")
    (folder / "part-000002.parquet").rename(folder / "part-000001.parquet")
    with pytest.raises(HilError, match="rows from 2, expected 1"):
        blocks.write_csv(tmp_path / "signals.csv")
    (folder / "part-000001.parquet").write_bytes(b"PAR1 cut short")
    with pytest.raises(HilError, match="part-000001.parquet: not a softhil signal block"):
        blocks.write_csv(tmp_path / "signals.csv")


def test_a_run_without_a_row_writes_the_header(tmp_path: Path) -> None:
    specs = [SignalSpec("kappa", "1/m", "", source="p.k")]
    SignalRecorder(tmp_path / "signals.csv", specs).close()
    assert (tmp_path / "signals.csv").read_text() == "time,kappa\n"
    assert not (tmp_path / "signals.parquet").exists()
    (tmp_path / "signals.csv").unlink()
    assert blocks.write_csv(tmp_path / "signals.csv") == 0  # the units sidecar's columns
    assert (tmp_path / "signals.csv").read_text() == "time,kappa\n"


def test_the_blocks_read_with_pyarrow_give_the_values_and_units(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The folder of blocks is one table to pyarrow (an independent Parquet reader): the values
    bit for bit as float64, NaN where a cell is empty, the units in every block's metadata."""
    pq = pytest.importorskip("pyarrow.parquet")
    now = [0.0]
    monkeypatch.setattr(recording.time, "monotonic", lambda: now[0])
    specs = [
        SignalSpec("kappa", "1/m", "curvature", source="p.k"),
        SignalSpec("p_a", "Pa", "pressure", source="p.p"),
        SignalSpec("phase", "", "phase", frame=("ControllerState", 1, "phase")),
    ]
    recorder = SignalRecorder(tmp_path / "signals.csv", specs)
    rng = np.random.default_rng(2)
    rows = []
    for k in range(50):
        row = [k * 0.01, float(rng.normal()), float(rng.normal(1e5, 1e3))]
        recorder.begin_row(row[0], row[1:])
        if k % 2:
            recorder.set_cells([("phase", k)])
        rows.append([*row, float(k) if k % 2 else math.nan])
        now[0] += 0.1 if k % 7 == 0 else 0.0
    recorder.close()
    table = pq.read_table(tmp_path / "signals.parquet")
    assert table.column_names == ["time", "kappa", "p_a", "phase"]
    got = np.array([table.column(c).to_numpy() for c in table.column_names])
    assert np.array_equal(got, np.array(rows).T, equal_nan=True)
    for part in (tmp_path / "signals.parquet").iterdir():
        metadata = pq.read_metadata(part).metadata
        assert json.loads(metadata[b"softhil.units"]) == {
            "time": "s",
            "kappa": "1/m",
            "p_a": "Pa",
            "phase": "",
        }


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
