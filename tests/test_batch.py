"""`hil batch`, `hil sweep`, `hil scenarios` and `hil run NAME` (issue 11).

The runs use a 0.3 s variant of the default scenario (one curvature step at 0.05 s, the realistic
camera, so that seeds change the results) offered as a built-in scenario `short` from a temporary
scenario folder. Acceptance: a batch run twice gives the same batch.json; a Dask LocalCluster run
gives the same batch.json as the local one.
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import re
import signal
import statistics
import subprocess
import sys
import time
import tomllib
from collections.abc import Iterator
from pathlib import Path

import pytest

from hil.batch import local, planning, reporting, runner
from hil.batch.tomlwrite import dumps_toml
from hil.batch.trial import metrics, run_trial
from hil.cli import main
from hil.errors import HilError, ScenarioError
from hil.scenario import (
    DEFAULT_SCENARIO,
    SCENARIO_FOLDERS,
    builtin_scenarios,
    resolve_scenario,
)

SHORT = re.sub(
    r"(?m)^sine = .*\n",
    "",
    DEFAULT_SCENARIO.read_text()
    .replace("duration = 10.0", "duration = 0.3")
    .replace('name = "default"', 'name = "short"')
    .replace("One segment tracking", "0.3 s: one segment tracking"),
)
SHORT = re.sub(r"(?m)^steps = .*$", "steps = [[0.0, 0.0], [0.05, 10.0]]", SHORT)
BROKEN = 'name = "broken"\ndescription = "a built-in with an unknown key"\nduraton = 1.0\n'


@pytest.fixture(scope="module")
def builtins(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """A scenario folder holding `short` and `broken`, in place of the package's."""
    folder = tmp_path_factory.mktemp("scenarios")
    (folder / "short.toml").write_text(SHORT)
    (folder / "broken.toml").write_text(BROKEN)
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr("hil.scenario.SCENARIO_FOLDERS", (folder,))
        yield folder


def hil(
    capsys: pytest.CaptureFixture[str], *argv: str | int | Path, reports: bool = False
) -> tuple[int, str, list[str]]:
    """Exit code, stdout and the lines of stderr of `hil ARGV`; a batch, sweep or run without
    its trials' plots and reports (`--no-reports`) unless `reports`."""
    words = [*map(str, argv)]
    if not reports and words[0] in ("batch", "sweep", "run"):
        words.append("--no-reports")
    code = main(words)
    out, err = capsys.readouterr()
    return code, out, err.splitlines()


@pytest.fixture(scope="module")
def local_batch(builtins: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("local") / "batch"
    code = main(["batch", "short", "--trials", "3", "--workers", "2", "--out", str(out)])
    assert code == 0
    return out


def load(path: Path) -> dict:
    return json.loads(path.read_text())


# ------------------------------------------------------------------ batch


def test_a_batch_run_twice_writes_the_same_batch_json(
    local_batch: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Acceptance; the second run has one worker and draws no trial's reports, so neither the
    worker count, the order in which trials finish nor --no-reports may show in the file."""
    out = tmp_path / "again"
    code, stdout, _ = hil(capsys, "batch", "short", "--trials", 3, "--workers", 1, "--out", out,
                          "--no-progress")  # fmt: skip
    assert code == 0 and "3 completed" in stdout
    assert (out / "batch.json").read_bytes() == (local_batch / "batch.json").read_bytes()
    drawn = sorted(p.name for p in (local_batch / "trial-002").glob("*.png"))
    assert drawn == ["curvature.png", "estimation.png", "piston.png", "pressures.png"]
    assert not list(out.glob("trial-*/*.png")) and (out / "batch.png").is_file()
    for name in ("can.log", "signals.csv"):
        assert (out / "trial-002" / name).read_bytes() == (
            local_batch / "trial-002" / name
        ).read_bytes()


def test_batch_json_trials_seeds_and_aggregates(local_batch: Path) -> None:
    report = load(local_batch / "batch.json")
    trials = report["trials"]
    assert report["seeds"] == [1, 2, 3] and [t["seed"] for t in trials] == [1, 2, 3]
    assert [t["index"] for t in trials] == [0, 1, 2]
    assert report["command"] == "hil batch short --trials 3" and report["scenario"] == "short"
    for trial in trials:  # each trial ran its own seed in its own folder
        folder = local_batch / trial["folder"]
        ran = tomllib.loads((folder / "scenario.toml").read_text())
        assert ran["seed"] == trial["seed"] and ran["duration"] == 0.3
        summary = load(folder / "summary.json")
        assert summary["seed"] == trial["seed"] and summary["status"] == "completed"
        assert trial["metrics"] == metrics(summary)
        assert trial["metrics"]["rms_tracking_error"] == summary["rms_tracking_error"]
    errors = [t["metrics"]["rms_tracking_error"] for t in trials]
    assert len(set(errors)) == 3, "the seeds made no difference: the camera noise is not seeded"
    stats = report["aggregate"]["rms_tracking_error"]
    assert stats["n"] == 3 and stats["min"] == min(errors) and stats["max"] == max(errors)
    assert math.isclose(stats["mean"], statistics.fmean(errors), rel_tol=1e-15)
    assert math.isclose(stats["std"], statistics.stdev(errors), rel_tol=1e-15)
    assert report["completed"] == 3 and report["failed"] == 0 and not report["failed_trials"]
    assert "success_rate" not in report  # the curvature task defines no success
    timing = load(local_batch / "timing.json")
    assert timing["executor"] == "local" and len(timing["trials"]) == 3
    assert (local_batch / "batch.png").read_bytes()[:4] == b"\x89PNG"


def test_parallel_trials_step_their_fmus_in_turn_unless_the_user_says(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Trials side by side on the cores leave no core to the kernel's worker thread: a worker
    of a parallel batch sets SOFTHIL_KERNEL_THREAD=0, a user's own value stays, one worker alone
    leaves it unset (each run decides)."""
    monkeypatch.delenv("SOFTHIL_KERNEL_THREAD", raising=False)
    local._share_cores(False)
    assert "SOFTHIL_KERNEL_THREAD" not in os.environ
    local._share_cores(True)
    assert os.environ["SOFTHIL_KERNEL_THREAD"] == "0"
    monkeypatch.setenv("SOFTHIL_KERNEL_THREAD", "1")
    local._share_cores(True)
    assert os.environ["SOFTHIL_KERNEL_THREAD"] == "1"


def test_metrics_leave_out_the_wall_clock(local_batch: Path) -> None:
    summary = load(local_batch / "trial-000" / "summary.json")
    clock = {"wall_time", "real_time_factor", "startup_time", "periods_on_kernel_thread"}
    assert clock <= summary.keys()
    names = set(metrics(summary))
    assert "rms_tracking_error" in names and "bus_load" in names
    assert not names & {*clock, "seed", "duration"}
    assert metrics({"a": 1, "b": 2.5, "ok": True, "t": {"x": 1}, "s": "x", "n": None}) == {
        "a": 1,
        "b": 2.5,
    }
    assert metrics({"controller_wall_time": 1.0, "planner_startup_time": 2.0}) == {}


def test_dask_local_cluster_gives_the_local_batch_json(
    local_batch: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """Acceptance: the same trials on a dask.distributed LocalCluster of two processes."""
    distributed = pytest.importorskip("distributed")
    out = tmp_path / "dask"
    with distributed.LocalCluster(
        n_workers=2, processes=True, threads_per_worker=1, dashboard_address=None
    ) as cluster:
        code, _, err = hil(capsys, "batch", "short", "--trials", 3, "--out", out, "--no-progress",
                           "--scheduler", cluster.scheduler_address)  # fmt: skip
        with distributed.Client(cluster) as client:
            workers = set(client.run(os.getpid).values())
    assert code == 0, err
    assert {t["pid"] for t in load(out / "timing.json")["trials"]} <= workers  # ran there
    assert (out / "batch.json").read_bytes() == (local_batch / "batch.json").read_bytes()
    timing = load(out / "timing.json")
    assert timing["executor"] == "dask" and timing["scheduler"] == cluster.scheduler_address


def test_overwrite_replaces_an_earlier_batch_and_keeps_foreign_files(
    local_batch: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """As `hil run --overwrite`: the files and trial folders softhil wrote are replaced, a
    user's files are kept, and a foreign folder named like a trial is refused before any run."""
    out = tmp_path / "batch"
    code, _, _ = hil(capsys, "batch", "short", "--trials", 1, "--workers", 1, "--out", out,
                     "--no-progress")  # fmt: skip
    assert code == 0
    (out / "notes.txt").write_text("mine")
    (out / "trial-000" / "notes.txt").write_text("mine too")
    (out / "trial-001").mkdir()
    (out / "trial-001" / "data.csv").write_text("foreign")
    before = (out / "batch.json").read_bytes()
    code, _, err = hil(capsys, "batch", "short", "--trials", 3, "--workers", 1, "--out", out,
                       "--no-progress", "--overwrite")  # fmt: skip
    assert code == 1 and len(err) == 1 and "trial-001 was not written by softhil" in err[0]
    assert (out / "batch.json").read_bytes() == before and not (out / "trial-002").exists()
    (out / "trial-001" / "data.csv").unlink()
    (out / "trial-001").rmdir()
    (out / "trial-000" / "summary.json").write_text("{}")  # replaced, not kept
    code, _, err = hil(capsys, "batch", "short", "--trials", 3, "--workers", 1, "--out", out,
                       "--no-progress", "--overwrite")  # fmt: skip
    assert code == 0, err
    assert (out / "batch.json").read_bytes() == (local_batch / "batch.json").read_bytes()
    assert (out / "notes.txt").read_text() == "mine"
    assert (out / "trial-000" / "notes.txt").read_text() == "mine too"
    assert load(out / "trial-000" / "summary.json")["status"] == "completed"
    # a run's --overwrite replaces an earlier run's files, not a whole batch (it removed them)
    code, _, err = hil(capsys, "run", "short", "--out", out, "--overwrite", "--no-progress")
    assert code == 1 and err == [
        f"hil: error: results folder {out} holds a batch (batch.json and its trials): "
        "--overwrite replaces an earlier run's files, not a whole batch; choose another --out"
    ]
    assert (out / "batch.json").read_bytes() == (local_batch / "batch.json").read_bytes()
    assert (out / "trial-002" / "summary.json").is_file()


def test_overwrite_with_fewer_trials_removes_the_earlier_batch_s_other_trials(
    builtins: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A batch of 3 overwritten by a batch of 1: trial-001 and trial-002 were the earlier
    batch's; their files go and so do they, unless a user's file is in one (then it stays,
    holding only that file, with a note); the manifest lists only what is there."""
    out = tmp_path / "batch"
    argv = ["batch", "short", "--workers", 1, "--out", out, "--no-progress"]
    code, _, _ = hil(capsys, *argv, "--trials", 3)
    assert code == 0
    (out / "trial-002" / "notes.txt").write_text("mine")
    code, _, err = hil(capsys, *argv, "--trials", 1, "--overwrite")
    assert code == 0, err
    assert not (out / "trial-001").exists()
    assert sorted(p.name for p in (out / "trial-002").iterdir()) == ["notes.txt"]
    assert err[0] == (
        f"hil: note: kept {out / 'trial-002'}: an earlier batch's trial, it holds files softhil "
        "did not write (notes.txt)"
    )
    listed = (out / ".softhil-manifest").read_text().split()
    assert "trial-000" in listed and "trial-001" not in listed and "trial-002" not in listed
    assert [t["folder"] for t in load(out / "batch.json")["trials"]] == ["trial-000"]


@pytest.mark.parametrize("signal_name", ["interrupted", "terminated"])
def test_a_stopped_batch_keeps_the_trials_that_finished(
    builtins: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    signal_name: str,
) -> None:
    """Ctrl-C or SIGTERM after two of three trials: batch.json holds those two with their
    metrics, the third as stopped, and says by what; the exit is the interrupt's."""
    from hil.errors import Terminated

    def two_then_stop(specs, workers, done):  # noqa: ANN001, ANN202
        for spec in specs[:2]:
            done(spec, run_trial(spec))
        raise KeyboardInterrupt if signal_name == "interrupted" else Terminated

    monkeypatch.setattr(runner, "run_local", two_then_stop)
    out = tmp_path / "batch"
    code, _, err = hil(capsys, "batch", "short", "--trials", 3, "--out", out, "--no-progress")
    assert code == (130 if signal_name == "interrupted" else 143)
    assert err[0] == (
        f"hil: note: {signal_name}: 2 of 3 trials finished; their results are in "
        f"{out / 'batch.json'}"
    )
    content = load(out / "batch.json")
    assert content["stopped"] == signal_name and content["completed"] == 2
    assert [t["status"] for t in content["trials"]] == ["completed", "completed", signal_name]
    assert content["trials"][0]["metrics"] and not content["trials"][2]["metrics"]
    assert content["failed_trials"][0]["index"] == 2
    assert not (out / "batch.png").exists() and not (out / ".softhil.lock").exists()


def test_trials_running_when_the_batch_is_stopped_are_kept(
    builtins: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Real worker processes: Ctrl-C as the first trial finishes; the second, running on the
    other worker, is waited for (a worker cannot stop between FMU steps) and reported too."""
    from concurrent.futures import as_completed

    def first_then_stop(futures):  # noqa: ANN001, ANN202
        yield next(iter(as_completed(futures)))
        raise KeyboardInterrupt

    monkeypatch.setattr(local, "as_completed", first_then_stop)
    out = tmp_path / "batch"
    code, _, _ = hil(capsys, "batch", "short", "--trials", 3, "--workers", 2, "--out", out,
                     "--no-progress")  # fmt: skip
    content = load(out / "batch.json")
    assert code == 130 and content["stopped"] == "interrupted"
    assert [t["status"] for t in content["trials"][:2]] == ["completed", "completed"]
    assert content["completed"] >= 2


def _batch_in_its_own_group(tmp_path: Path) -> tuple[subprocess.Popen[str], Path]:
    """`hil batch` of 3 trials on one worker, in a process group of its own as a shell's job
    is, once its first trial is recording (a 60 s trial: seconds of work)."""
    scenario = tmp_path / "long.toml"
    scenario.write_text(SHORT.replace("duration = 0.3", "duration = 60.0"))
    out = tmp_path / "batch"
    run = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "hil",
            "batch",
            str(scenario),
            "--trials",
            "3",
            "--workers",
            "1",
            "--out",
            str(out),
            "--no-progress",
        ],  # fmt: skip
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    blocks = out / "trial-000" / "signals.parquet"  # the first block: written after 0.25 s
    for _ in range(600):
        if any(blocks.glob("part-*.parquet")) or run.poll() is not None:
            break
        time.sleep(0.1)
    assert run.poll() is None, run.communicate()
    return run, out


def _group_left(group: int) -> list[int]:
    """Processes still in process group `group` (zombies aside) once those that end with the
    batch have had up to 30 s to do so (a worker and the forkserver see the batch's pipes
    close, then exit; on a loaded machine that is not at once)."""
    deadline = time.monotonic() + 30.0
    while True:
        left = []
        for stat in Path("/proc").glob("[0-9]*/stat"):
            with contextlib.suppress(OSError):
                fields = stat.read_text().rpartition(")")[2].split()
                if int(fields[2]) == group and fields[0] != "Z":
                    left.append(int(stat.parent.name))
        if not left or time.monotonic() > deadline:
            return left
        time.sleep(0.1)


def _ctrl_c(tmp_path: Path, presses: int) -> tuple[subprocess.Popen[str], Path, str]:
    """The batch of `_batch_in_its_own_group` given Ctrl-C `presses` times, 0.5 s apart, as a
    terminal gives it (to the whole job); (the finished batch, its folder, its stderr)."""
    run, out = _batch_in_its_own_group(tmp_path)
    try:
        for press in range(presses):
            if press:
                time.sleep(0.5)
            os.killpg(run.pid, signal.SIGINT)
        _, err = run.communicate(timeout=120)
    finally:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(run.pid, signal.SIGKILL)
    return run, out, err


def test_ctrl_c_at_a_terminal_lets_the_running_trial_finish(tmp_path: Path) -> None:
    """A terminal's Ctrl-C reaches every process of the job: the workers ignore it, so the
    running trial completes and is reported, as the README says; the others never start."""
    run, out, err = _ctrl_c(tmp_path, 1)
    assert run.returncode == 130, err
    content = load(out / "batch.json")
    assert content["stopped"] == "interrupted"
    assert [t["status"] for t in content["trials"]] == ["completed", "interrupted", "interrupted"]
    assert load(out / "trial-000" / "summary.json")["status"] == "completed"
    assert _group_left(run.pid) == []


def test_a_second_ctrl_c_stops_the_running_trial_and_keeps_what_it_recorded(
    tmp_path: Path,
) -> None:
    """The second Ctrl-C, while the batch waits for its running trial, stops that trial as a
    terminated run (its folder keeps its signals, can.log and a summary saying so); batch.json
    is written and the batch exits 130 with no process of its job left behind."""
    run, out, err = _ctrl_c(tmp_path, 2)
    assert run.returncode == 130, err
    content = load(out / "batch.json")
    assert content["stopped"] == "interrupted" and content["completed"] == 0
    summary = load(out / "trial-000" / "summary.json")
    assert summary["status"] == "terminated", summary
    assert (out / "trial-000" / "can.log").stat().st_size > 0
    assert "stopping the running trials" in err
    assert _group_left(run.pid) == []


def test_an_unreachable_scheduler_is_one_line(
    builtins: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    dask = pytest.importorskip("dask")
    with dask.config.set({"distributed.comm.timeouts.connect": "0.2s"}):
        code, _, err = hil(capsys, "batch", "short", "--trials", 1, "--out", tmp_path / "x",
                           "--scheduler", "tcp://127.0.0.1:1", "--no-progress")  # fmt: skip
    assert code == 1 and len(err) == 1 and "--scheduler tcp://127.0.0.1:1" in err[0]
    assert not (tmp_path / "x").exists()
    # refused at once, not after dask's connect timeout (30 s by default)
    code, _, err = hil(capsys, "batch", "short", "--trials", 1, "--out", tmp_path / "x",
                       "--scheduler", "tcp://127.0.0.1:1", "--no-progress")  # fmt: skip
    assert code == 1 and err == [
        "hil: error: --scheduler tcp://127.0.0.1:1: nothing listens on 127.0.0.1:1 (is the dask "
        "scheduler running there?)"
    ]


@pytest.mark.parametrize("address", ["garbage", "tcp://host:x"])
def test_a_malformed_scheduler_address_is_one_line_at_once(
    builtins: Path, tmp_path: Path, address: str
) -> None:
    """Refused before dask makes a Client: a half-made one kept the process from exiting for
    60 s and printed a traceback after the error (run as a user would, in its own process)."""
    pytest.importorskip("distributed")
    done = subprocess.run(
        [sys.executable, "-m", "hil", "batch", str(builtins / "short.toml"), "--trials", "1",
         "--out", str(tmp_path / "x"), "--scheduler", address, "--no-progress"],
        cwd=Path(__file__).parents[1], capture_output=True, text=True, timeout=40,  # this hil
    )  # fmt: skip
    assert done.returncode == 1, done.stderr
    lines = done.stderr.splitlines()
    assert len(lines) == 1 and f"--scheduler {address}: not a scheduler address" in lines[0]
    assert not (tmp_path / "x").exists()


def _examples() -> list[str]:
    """Every `hil batch`/`hil sweep` command the help and the README show."""
    from hil.cli.batch import BATCH_EXAMPLES, SWEEP_EXAMPLES

    readme = (Path(__file__).parents[1] / "README.md").read_text(encoding="utf-8")
    lines = [*BATCH_EXAMPLES.splitlines(), *SWEEP_EXAMPLES.splitlines()]
    lines += [line for line in readme.splitlines() if line.startswith("    hil ")]
    commands = [re.split(r"\s{2,}", line.strip())[0] for line in lines]
    return [c for c in commands if c.startswith(("hil batch", "hil sweep"))]


@pytest.mark.parametrize("command", _examples())
def test_every_example_command_plans(
    command: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The examples users copy are plans that load (each --set key exists, each value fits);
    `hil sweep --set segment.bore=...` in the help named a key the scenario does not have."""
    import shlex

    import hil.cli.batch

    planned: list[planning.Plan] = []
    monkeypatch.setattr(
        hil.cli.batch,
        "run_plan",
        lambda plan, *a, **k: planned.append(plan) or {"failed_trials": []},
    )
    monkeypatch.setattr(hil.cli.batch, "_print", lambda *a: None)
    # the package's built-ins, even after a test of this module put `builtins` in their place
    # (a module fixture: in file order, as `pytest -n0` runs, it is still in place here)
    monkeypatch.setattr("hil.scenario.SCENARIO_FOLDERS", SCENARIO_FOLDERS)
    monkeypatch.chdir(tmp_path)
    (tmp_path / "my.toml").write_text(DEFAULT_SCENARIO.read_text())
    argv = shlex.split(command.replace("HOST", "127.0.0.1"))[1:]
    assert main([*argv, "--out", str(tmp_path / "out")]) == 0, command
    assert len(planned) == 1, command
    assert len(planned[0].trials) >= 1


# ------------------------------------------------------------------ sweep


def test_sweep_grid_folders_and_a_failing_value(
    builtins: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A 2x2 grid: a 3 kPa over-pressure limit stops the strict run at the step (at run time,
    not at load), the others complete; every trial keeps its folder and the values it ran."""
    out = tmp_path / "sweep"
    code, stdout, err = hil(capsys, "sweep", "short", "--set", "safety.max_pressure=3000,60000",
                            "--set", "controller.estimator=kf,ukf", "--seed", 7, "--out", out,
                            "--no-progress")  # fmt: skip
    assert code == 1 and err[-1].startswith("hil: error: 2 of 4 trials failed")
    assert "seed 7" in err[-1] and "over-pressure" in err[-1]
    report = load(out / "batch.json")
    expected = [(3000, "kf"), (3000, "ukf"), (60000, "kf"), (60000, "ukf")]
    for trial, (pressure, estimator) in zip(report["trials"], expected, strict=True):
        ran = tomllib.loads((out / trial["folder"] / "scenario.toml").read_text())
        assert ran["safety"]["max_pressure"] == pressure
        assert trial["overrides"] == {
            "safety.max_pressure": pressure,
            "controller.estimator": estimator,
        }
        assert ran["controller"]["estimator"] == estimator and ran["seed"] == trial["seed"] == 7
        assert load(out / trial["folder"] / "summary.json")["seed"] == 7
        if pressure == 3000:
            assert trial["status"] == "failed" and "over-pressure" in trial["error"]
            assert not trial["metrics"]
        else:
            assert trial["status"] == "completed" and trial["metrics"]["rms_tracking_error"] > 0
    assert [(f["index"], f["seed"]) for f in report["failed_trials"]] == [(0, 7), (1, 7)]
    assert report["grid"]["keys"] == ["safety.max_pressure", "controller.estimator"]
    assert [p["trials"] for p in report["points"]] == [[0], [1], [2], [3]]
    assert [p["failed"] for p in report["points"]] == [1, 1, 0, 0]
    assert report["points"][2]["aggregate"]["rms_tracking_error"]["n"] == 1
    assert report["aggregate"]["rms_tracking_error"]["n"] == 2
    assert len(list(out.glob("trial-*/scenario.toml"))) == 4
    assert "[safety.max_pressure=60000 controller.estimator=ukf]" in stdout


def test_trial_warnings_reach_batch_json_and_the_terminal(
    builtins: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A trial that completes with warnings is not a silent success: batch.json keeps each
    trial's warnings (here a bus too slow for its traffic on one, and the short scenario's step
    that cannot settle in 0.25 s on both) and lists them in `warned_trials`; the terminal names
    each trial's first warning."""
    out = tmp_path / "warned"
    code, _, err = hil(capsys, "sweep", "short", "--set", "bus.bitrate=1000000,50000",
                       "--out", out, "--no-progress")  # fmt: skip
    assert code == 0, err
    report = load(out / "batch.json")
    for trial in report["trials"]:
        summary = load(out / trial["folder"] / "summary.json")
        assert trial["status"] == "completed" and trial["warnings"] == summary["warnings"]
    fast, slow = report["trials"]
    assert not any("bus load" in w for w in fast["warnings"])
    assert len(slow["warnings"]) == 2 and slow["warnings"][0].startswith("bus load 161 %")
    assert report["warned_trials"] == [
        {"index": t["index"], "seed": 1, "folder": t["folder"], "warnings": t["warnings"]}
        for t in (fast, slow)
    ]
    assert [p["warned"] for p in report["points"]] == [1, 1] and report["warned"] == 2
    assert err == [
        "  warning: trial 0 (seed 1): a step never settled within its hold (settling_time is null)",
        f"  warning: trial 1 (seed 1): {slow['warnings'][0]} (and 1 more)",
    ]


def test_a_trial_without_warnings_has_none_in_batch_json(builtins: Path, tmp_path: Path) -> None:
    plan = planning.make_plan(
        builtins / "short.toml", kind="batch", command="c", out=tmp_path / "p", trials=3
    )
    done = {"status": "completed", "error": None, "metrics": {"e": 1.0}, "success": None}
    outcomes = [{**done, "warnings": []}, {**done, "warnings": ["w"]}, dict(done)]
    report = reporting.report(plan, outcomes)
    assert ["warnings" in t for t in report["trials"]] == [False, True, False]
    assert report["warned"] == 1 and [t["index"] for t in report["warned_trials"]] == [1]


def test_the_terminal_names_five_warned_trials_and_counts_the_rest(
    builtins: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from hil.cli.batch import WARNED_SHOWN, _print

    plan = planning.make_plan(
        builtins / "short.toml", kind="batch", command="c", out=tmp_path / "p", trials=8
    )
    done = {"status": "completed", "error": None, "metrics": {"e": 1.0}, "success": None}
    outcomes = [{**done, "warnings": [f"w{i}"] if i != 2 else []} for i in range(8)]
    _print(plan, reporting.report(plan, outcomes))
    err = capsys.readouterr().err.splitlines()
    assert WARNED_SHOWN == 5 and err == [
        *(f"  warning: trial {i} (seed {i + 1}): w{i}" for i in (0, 1, 3, 4, 5)),
        "  warning: 2 more trials with warnings: warned_trials in batch.json",
    ]


@pytest.mark.parametrize(
    ("option", "reason"),
    [
        ("controller.crossover=-1.0", "controller.crossover"),
        ("controller.crossovr=1.0", "unknown key"),
        ("valve.open_time=0.1", "robot.valve: unknown key"),
        ("camera.noise=0.001,fast", "camera.noise: must be a number"),
        ("controller.crossover", "expected section.key=value"),
        ("controller.crossover=1,1", "repeated"),
        ("controller.crossover=[1", "not a TOML value"),
        ("seed=1,2", "use --seed and --trials"),
        ("controller.crossover=1,1.0", "repeated"),  # the same number
        ("camra.noise=0.001", "robot.camra: unknown key"),
        ("camra.noise=0.001", "; camra is not a top-level key either (bus, camera, "),
    ],
)
def test_set_errors_are_one_line_before_anything_runs(
    builtins: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], option: str, reason: str
) -> None:
    out = tmp_path / "never"
    code, _, err = hil(capsys, "sweep", "short", "--set", option, "--out", out)
    assert code == 1 and len(err) == 1, err
    assert err[0].startswith(f"hil: error: --set {option.partition('=')[0]}") and reason in err[0]
    assert not out.exists()


def test_a_bare_date_in_set_is_the_string_it_was_typed_as(builtins: Path, tmp_path: Path) -> None:
    """A bare word is a string, and so is an unquoted date: `recording.start=2016-01-01T00:00:00Z`
    sweeps the instant the README writes that way (it was a TypeError traceback)."""
    option = planning.parse_set("recording.start=2016-01-01T00:00:00Z,1979-05-27T07:32:00Z")
    assert option.values == ("2016-01-01T00:00:00Z", "1979-05-27T07:32:00Z")
    assert planning.parse_set("a.b=[1979-05-27]").values == (["1979-05-27"],)
    spaced = planning.parse_set("recording.start=2016-01-01 00:00:00Z")  # TOML allows the space
    assert spaced.values == ("2016-01-01 00:00:00Z",)  # as typed, not re-formatted
    plan = planning.make_plan(builtins / "short.toml", kind="sweep", command="c",
                           out=tmp_path / "p", trials=1, overrides=[option])  # fmt: skip
    texts = [tomllib.loads(spec.scenario_text)["recording"]["start"] for spec in plan.trials]
    assert texts == ["2016-01-01T00:00:00Z", "1979-05-27T07:32:00Z"]


def test_a_batch_too_big_is_refused_before_anything_is_checked(
    builtins: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """10^6 grid points or 10^8 seeds were planned in silence for minutes (and GB)."""
    values = ",".join(str(0.5 + i / 1000) for i in range(1000))
    out = tmp_path / "never"
    code, _, err = hil(capsys, "sweep", "short", "--set", f"controller.crossover={values}",
                       "--set", f"camera.noise={values}", "--out", out)  # fmt: skip
    assert code == 1 and err == [
        "hil: error: --set: 1000000 grid points x 1 trial = 1000000 trials; at most "
        f"{planning.MAX_TRIALS} in one batch or sweep (split it: fewer values, or --seed and "
        "--trials in parts)"
    ]
    code, _, err = hil(capsys, "batch", "short", "--trials", 100_000_000, "--out", out)
    assert code == 1 and err[0].startswith("hil: error: --trials: 100000000 trials; at most ")
    assert not out.exists()
    assert planning.MAX_TRIALS == 10_000
    noted = planning.make_plan(
        builtins / "short.toml",
        kind="sweep",
        command="c",
        out=out,
        trials=1,
        overrides=[
            planning.parse_set("camera.noise=0,0.001,0.002"),
            planning.parse_set("controller.crossover=" + ",".join(values.split(",")[:30])),
        ],
    )
    assert len(noted.points) == 3 * 30 > planning.CHECK_NOTE_POINTS
    assert capsys.readouterr().err.splitlines() == [
        "hil: note: checking 90 grid points before anything runs"
    ]  # fmt: skip
    largest = planning.make_plan(
        builtins / "short.toml", kind="batch", command="c", out=out, trials=planning.MAX_TRIALS
    )
    assert len(largest.trials) == planning.MAX_TRIALS


def test_parse_set_values_and_the_robot_fallback() -> None:
    crossover = planning.parse_set("controller.crossover=0.5,1,2e-1")
    assert crossover.key == "controller.crossover" and crossover.values == (0.5, 1, 0.2)
    assert planning.parse_set("segment.bore=0.02").key == "robot.segment.bore"
    assert planning.parse_set("robot.segments=1,2").key == "robot.segments"
    assert planning.parse_set("duration=0.2").key == "duration"
    assert planning.parse_set("controller.estimator=kf,ukf").values == ("kf", "ukf")
    assert planning.parse_set('a.b="x,y",true,[1, 2]').values == ("x,y", True, [1, 2])
    data = {"robot": {"kind": "planar_arm"}, "camera": {"noise": 0.0}}
    changed = planning.apply_overrides(
        data, [("robot.segment.3.bore", 0.02), ("camera.noise", 1.0)]
    )
    assert changed == {
        "robot": {"kind": "planar_arm", "segment": {"3": {"bore": 0.02}}},
        "camera": {"noise": 1.0},
    }
    assert data["camera"]["noise"] == 0.0  # the parsed scenario is not touched
    with pytest.raises(HilError, match="camera.noise is not a table"):
        planning.apply_overrides(data, [("camera.noise.x", 1.0)])


def test_toml_writer_round_trip(builtins: Path) -> None:
    for scenario in [DEFAULT_SCENARIO, builtins / "short.toml"]:
        data = tomllib.loads(scenario.read_text())
        assert tomllib.loads(dumps_toml(data)) == data
    data = {
        "name": 'quote " backslash \\ newline \n tab \t del \x7f e\u0301 \U0001f41f',
        "f": [0.1, 1e-300, 1.7976931348623157e308, -0.0, 5e-324, math.inf, -math.inf],
        "i": [0, -1, 2**63 - 1],
        "b": [True, False],
        "empty": [],
        "nested": [[1, 2], ["a"], [{"x": 1}]],
        "key with space": {"inline": {"a": 1}, "deep": {"er": {"still": "x"}}},
        "connections": [
            {"from": "a.b", "to": "c.d", "sub": {"gain": 2.0}},
            {"from": "e.f", "to": "g.h", "sub": {"gain": 3.0}},
        ],
        "table": {},
    }
    assert tomllib.loads(dumps_toml(data)) == data
    assert math.isnan(tomllib.loads(dumps_toml({"x": math.nan}))["x"])


def test_success_rate_counts_failed_trials_as_unsuccessful(builtins: Path, tmp_path: Path) -> None:
    """Later tasks' summaries carry a boolean `success`; the rate is over every trial."""
    plan = planning.make_plan(
        builtins / "short.toml", kind="batch", command="c", out=tmp_path / "p", trials=4
    )
    outcomes = [
        {"status": "completed", "error": None, "metrics": {"e": 1.0}, "success": True},
        {"status": "completed", "error": None, "metrics": {"e": 3.0}, "success": False},
        {"status": "completed", "error": None, "metrics": {"e": 2.0}, "success": True},
        {"status": "failed", "error": "boom", "metrics": {}, "success": None},
    ]
    report = reporting.report(plan, outcomes)
    assert report["success_rate"] == 0.5
    assert report["aggregate"]["e"] == {"mean": 2.0, "std": 1.0, "min": 1.0, "max": 3.0, "n": 3}
    assert report["failed_trials"] == [
        {"index": 3, "seed": 4, "folder": "trial-003", "error": "boom"}
    ]
    assert [t.get("success") for t in report["trials"]] == [True, False, True, None]
    assert not (tmp_path / "p").exists()  # planning writes nothing


# ------------------------------------------------------------------ scenarios and run NAME


def test_hil_scenarios_lists_default(capsys: pytest.CaptureFixture[str], monkeypatch) -> None:
    monkeypatch.setattr("hil.scenario.SCENARIO_FOLDERS", SCENARIO_FOLDERS)  # the package's
    code, stdout, _ = hil(capsys, "scenarios")
    description = tomllib.loads(DEFAULT_SCENARIO.read_text())["description"]
    assert code == 0 and re.search(rf"(?m)^default +{re.escape(description)}$", stdout)


def test_every_toml_in_the_scenario_folder_is_a_builtin(
    builtins: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    found = builtin_scenarios()
    assert list(found) == ["broken", "short"]
    assert found["broken"].description == "a built-in with an unknown key"
    code, stdout, _ = hil(capsys, "scenarios")
    assert code == 0 and stdout.splitlines()[1].startswith("short   0.3 s: one segment")


def test_run_name_resolves_builtins_files_first_and_lists_the_known(
    builtins: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch
) -> None:
    assert resolve_scenario("short") == builtins / "short.toml"
    monkeypatch.chdir(tmp_path)
    Path("short").write_text(SHORT)  # an existing path wins over a built-in name
    assert resolve_scenario("short") == Path("short")
    # the built-in's own problem is reported with its file: the name was resolved to it
    code, _, err = hil(capsys, "run", "broken", "--inprocess")
    assert code == 1 and len(err) == 1 and f"{builtins / 'broken.toml'}: duraton" in err[0]
    code, _, err = hil(capsys, "run", "nonesuch", "--inprocess")
    assert code == 1 and len(err) == 1 and "nonesuch" in err[0] and "broken, short" in err[0]
    with pytest.raises(ScenarioError, match="built-in: broken, short"):
        resolve_scenario("nonesuch.toml")


def test_no_progress_bar_where_stderr_is_not_a_terminal(
    builtins: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """As hil run: tqdm's bar is for a terminal, not for a log that stderr is redirected to."""
    code, _, err = hil(capsys, "batch", "short", "--trials", 1, "--workers", 1,
                       "--out", tmp_path / "b")  # fmt: skip
    assert code == 0
    assert not any("trial/s" in line or "it/s" in line or "\r" in line for line in err), err
