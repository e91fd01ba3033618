"""rigbus.pycan: python-can imported without asammdf, its MF4 reader and writer still whole.

Each check runs in a fresh interpreter: what is imported depends on what was imported before.
"""

from __future__ import annotations

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def run_fresh(code: str, cwd: Path) -> dict[str, object]:
    """`code` in a new interpreter; it prints one JSON object, returned."""
    done = subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        cwd=cwd,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("first", ["rigbus", "hil", "controllers", "robots"])
def test_importing_softhil_imports_python_can_without_asammdf_pandas_or_sympy(
    first: str, tmp_path: Path
) -> None:
    seen = run_fresh(
        f"""
        import json, sys
        import {first}
        import can
        print(json.dumps({{name: name in sys.modules
                          for name in ("can", "asammdf", "pandas", "sympy")}}))
        """,
        ROOT,
    )
    assert seen == {"can": True, "asammdf": False, "pandas": False, "sympy": False}


def test_the_mf4_writer_and_reader_handed_out_before_load_asammdf_on_first_use(
    tmp_path: Path,
) -> None:
    pytest.importorskip("asammdf")
    seen = run_fresh(
        f"""
        import json, sys
        import rigbus
        import can
        from rigbus.pycan import mf4_loaded
        before = mf4_loaded()
        path = {str(tmp_path / "frames.mf4")!r}
        sent = [can.Message(timestamp=0.25 * i, arbitration_id=0x100 + i,
                            data=bytes([i, 2 * i, 255 - i]), is_extended_id=False)
                for i in range(5)]
        with can.Logger(path) as log:   # the class can.Logger chose at import, by suffix
            for msg in sent:
                log.on_message_received(msg)
        read = list(can.LogReader(path))
        print(json.dumps({{
            "before": before, "after": mf4_loaded(), "asammdf": "asammdf" in sys.modules,
            "writer": type(can.Logger(path + ".2.mf4")).__name__,
            "ids": [m.arbitration_id for m in read],
            "data": [m.data.hex() for m in read],
            "times": [m.timestamp for m in read],
        }}))
        """,
        ROOT,
    )
    assert seen["before"] is False and seen["after"] is True and seen["asammdf"] is True
    assert seen["writer"] == "MF4Writer"
    assert seen["ids"] == [0x100, 0x101, 0x102, 0x103, 0x104]
    assert seen["data"] == ["0000ff", "0102fe", "0204fd", "0306fc", "0408fb"]
    assert seen["times"] == pytest.approx([0.0, 0.25, 0.5, 0.75, 1.0])


def test_without_asammdf_the_mf4_writer_fails_as_python_cans_own_does(tmp_path: Path) -> None:
    seen = run_fresh(
        f"""
        import json, sys
        sys.modules["asammdf"] = None     # asammdf not installed
        sys.modules.pop("can", None)
        import rigbus
        import can
        from rigbus.pycan import load_mf4
        try:
            can.Logger({str(tmp_path / "x.mf4")!r})
            error = ""
        except Exception as exc:
            error = type(exc).__name__ + ": " + str(exc)
        print(json.dumps({{"load": load_mf4(), "error": error}}))
        """,
        ROOT,
    )
    assert seen["load"] is False
    assert "asammdf" in str(seen["error"]).lower()


def test_python_can_imported_first_is_left_whole(tmp_path: Path) -> None:
    pytest.importorskip("asammdf")
    seen = run_fresh(
        """
        import json, sys
        import can
        import rigbus
        from rigbus.pycan import mf4_loaded
        print(json.dumps({"loaded": mf4_loaded(), "asammdf": "asammdf" in sys.modules}))
        """,
        ROOT,
    )
    assert seen == {"loaded": True, "asammdf": True}
