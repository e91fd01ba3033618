"""The FMU cache is verified against its manifest before use and repaired, with one note line."""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from hil.fmu import build as build_module
from hil.fmu.build import MANIFEST, build_fmu, cache_damage
from hil.fmu.slave import FmuSlave

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture
def cache(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """An empty private cache (the sources stay the checkout's, read only)."""
    root = tmp_path / "cache"
    monkeypatch.setenv("SOFTHIL_CACHE_DIR", str(root))
    return root


def _steps(built) -> float:  # noqa: ANN001 - BuiltFmu
    """Load the extracted folder the way `hil run` does and take one step."""
    with FmuSlave(built, "cache_check") as slave:
        slave.do_step(0.0, 1e-3)
        return float(slave.get("x"))


def test_manifest_lists_every_file_with_its_digest(cache: Path) -> None:
    built = build_fmu("DriveCylinder")
    entry = built.path.parent
    lines = (entry / MANIFEST).read_text().splitlines()
    listed = {line.split("  ", 1)[1]: line.split("  ", 1)[0] for line in lines}
    files = {
        p.relative_to(entry).as_posix()
        for p in entry.rglob("*")
        if p.is_file() and p.name != MANIFEST
    }
    assert set(listed) == files
    assert "unzipped/binaries/linux64/DriveCylinder.so" in listed
    assert listed["DriveCylinder.fmu"] == hashlib.sha256(built.path.read_bytes()).hexdigest()
    assert cache_damage(entry) is None


def test_corrupt_shared_object_is_rebuilt_with_a_note(
    cache: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    built = build_fmu("DriveCylinder")
    so = built.unzipdir / "binaries" / "linux64" / "DriveCylinder.so"
    good = so.read_bytes()
    stat = so.stat()
    # Same size and mtime: only the content tells.
    so.write_bytes(good[:1000] + bytes([good[1000] ^ 0xFF]) + good[1001:])
    os.utime(so, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    capsys.readouterr()
    again = build_fmu("DriveCylinder")
    err = capsys.readouterr().err
    assert err == (
        "hil: note: rebuilt DriveCylinder: cached unzipped/binaries/linux64/DriveCylinder.so "
        "did not match its digest\n"
    )
    assert again.unzipdir == built.unzipdir
    assert so.read_bytes() == good
    assert cache_damage(again.path.parent) is None
    _steps(again)
    build_fmu("DriveCylinder")  # sound now: no second note
    assert capsys.readouterr().err == ""


def test_deleted_unzipped_folder_is_rebuilt(
    cache: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    built = build_fmu("FeaSegment")
    shutil.rmtree(built.unzipdir)
    capsys.readouterr()
    again = build_fmu("FeaSegment")
    err = capsys.readouterr().err
    assert err.startswith("hil: note: rebuilt FeaSegment: cached unzipped/")
    assert "is missing (and " in err and err.count("\n") == 1
    assert (again.unzipdir / "binaries" / "linux64" / "FeaSegment.so").is_file()


def test_missing_manifest_or_zip_is_damage(cache: Path) -> None:
    built = build_fmu("DriveCylinder")
    entry = built.path.parent
    built.path.unlink()
    assert cache_damage(entry) == "cached DriveCylinder.fmu is missing"
    (entry / MANIFEST).unlink()
    assert MANIFEST in str(cache_damage(entry))
    build_fmu("DriveCylinder")
    assert cache_damage(entry) is None


def test_hil_fmu_build_repairs_and_says_so(cache: Path) -> None:
    built = build_fmu("DriveCylinder")
    so = built.unzipdir / "binaries" / "linux64" / "DriveCylinder.so"
    so.write_bytes(b"\0" * 100)
    env = dict(os.environ, SOFTHIL_CACHE_DIR=str(cache))
    result = subprocess.run(
        [sys.executable, "-m", "hil", "fmu", "build", "DriveCylinder"],
        cwd=ROOT,
        env=env,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert result.returncode == 0, result.stderr
    assert result.stderr == (
        "hil: note: rebuilt DriveCylinder: cached unzipped/binaries/linux64/DriveCylinder.so "
        "did not match its digest\n"
    )
    assert cache_damage(built.path.parent) is None
    _steps(built)


def test_repair_racing_another_build_uses_the_complete_one(
    cache: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Another process installs its build while ours is compiling: no half-written entry is
    ever visible, and both end with one sound entry."""
    built = build_fmu("DriveCylinder")
    entry = built.path.parent
    (built.unzipdir / "modelDescription.xml").write_text("damaged")
    real_build_into = build_module._build_into
    seen: list[str | None] = []

    def build_into_while_another_installs(work: Path, *args: object) -> None:
        real_build_into(work, *args)  # type: ignore[arg-type]
        if not seen:  # the "other process": a complete build renamed into place now
            seen.append("other")
            build_fmu("DriveCylinder")
            seen.append(cache_damage(entry))

    monkeypatch.setattr(build_module, "_build_into", build_into_while_another_installs)
    again = build_fmu("DriveCylinder")
    assert seen == ["other", None]
    assert cache_damage(entry) is None
    assert [p.name for p in entry.parent.iterdir()] == [entry.name]  # no leftovers
    _steps(again)


def test_two_processes_building_at_once(cache: Path) -> None:
    script = (
        "from hil.fmu.build import build_fmu, cache_damage\n"
        "b = build_fmu('FeaSegment')\n"
        "assert cache_damage(b.path.parent) is None\n"
    )
    env = dict(os.environ, SOFTHIL_CACHE_DIR=str(cache))
    procs = [subprocess.Popen([sys.executable, "-c", script], cwd=ROOT, env=env) for _ in range(2)]
    assert [p.wait(300) for p in procs] == [0, 0]
    assert len(list((cache / "fmus").iterdir())) == 1


def test_a_build_finishing_second_keeps_the_sound_entry_in_place(
    cache: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Two workers building the same FMU into an empty cache (parallel tests, two `hil run`):
    the one finishing second drops its build, so the entry the first one loads stays put."""
    real_build_into = build_module._build_into
    first: list[int] = []

    def build_into_while_another_installs(work: Path, *args: object) -> None:
        real_build_into(work, *args)  # type: ignore[arg-type]
        if not first:  # the "other process" installs its build while ours compiles
            first.append(0)
            other = build_fmu("FeaSegment")
            first[0] = (other.unzipdir / "modelDescription.xml").stat().st_ino

    monkeypatch.setattr(build_module, "_build_into", build_into_while_another_installs)
    ours = build_fmu("FeaSegment")
    assert (ours.unzipdir / "modelDescription.xml").stat().st_ino == first[0]
    assert [p.name for p in ours.path.parent.parent.iterdir()] == [ours.path.parent.name]
    assert cache_damage(ours.path.parent) is None
    with FmuSlave(ours, "kept") as slave:
        slave.do_step(0.0, 1e-3)


@pytest.mark.parametrize("where", ["under-a-file", "read-only"])
def test_a_cache_folder_that_cannot_be_used_is_one_line(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], where: str
) -> None:
    """SOFTHIL_CACHE_DIR under a file, or read-only: one line naming the variable and the
    folder, from `hil fmu build` and from `hil run` (a FileNotFoundError or OSError traceback
    before, and a run folder without a summary); the run's summary.json says why it failed."""
    from hil.cli import main

    if where == "under-a-file":
        (tmp_path / "a-file").write_text("x")
        cache = tmp_path / "a-file" / "cache"
    else:
        cache = tmp_path / "ro"
        cache.mkdir()
        cache.chmod(0o555)
        if os.access(cache, os.W_OK):  # root ignores the mode: a read-only bind is not here
            pytest.skip("this user writes into read-only folders")
    monkeypatch.setenv("SOFTHIL_CACHE_DIR", str(cache))
    assert main(["fmu", "build", "GasSource", "--force"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"hil: error: SOFTHIL_CACHE_DIR {cache}"), err
    assert err[0].endswith("; set SOFTHIL_CACHE_DIR to a folder you can write")
    out = tmp_path / "run"
    assert main(["run", "--out", str(out), "--no-progress"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"hil: error: SOFTHIL_CACHE_DIR {cache}"), err
    summary = json.loads((out / "summary.json").read_text())
    assert summary["status"] == "failed" and summary["error"] == err[0].removeprefix("hil: error: ")
