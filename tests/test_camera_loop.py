"""The realistic camera in the closed loop (issue 9's acceptance): the chosen estimator beats the
raw inversion, the loop tracks as well as with an ideal camera, it survives dropouts, occlusions
and outliers, latency compensation helps, and every estimator is deterministic."""

from __future__ import annotations

import contextlib
import json
from pathlib import Path

import numpy as np
import pytest

from controllers import kinematics
from controllers.estimation import MarkerFrame
from hil.bus.loopback import LoopbackHub
from hil.cycles import config_beside
from hil.estimation import estimation_report, marker_residuals, measured_cycles, score
from hil.run import RunOptions, run_scenario
from hil.scenario import DEFAULT_SCENARIO, load_scenario
from hil.summary import read_signals

IDEAL = (
    ("noise = 0.0005", "noise = 0.0"),
    ("dropout = 0.01", "dropout = 0.0"),
    ("outlier_rate = 0.001", "outlier_rate = 0.0"),
)


def scenario(tmp_path: Path, name: str, *edits: tuple[str, str]) -> Path:
    text = DEFAULT_SCENARIO.read_text()
    for old, new in edits:
        assert old in text, old
        text = text.replace(old, new)
    path = tmp_path / f"{name}.toml"
    path.write_text(text.replace('name = "default"', f'name = "{name}"'))
    return path


def run(path: Path, out: Path, process: bool = False, bus: str | None = None):  # noqa: ANN201
    return run_scenario(
        load_scenario(path), RunOptions(out=out, inprocess=not process, progress=False, bus=bus)
    )


@pytest.fixture(scope="module")
def default_run(tmp_path_factory: pytest.TempPathFactory):  # noqa: ANN201
    folder = tmp_path_factory.mktemp("camera")
    return run(DEFAULT_SCENARIO, folder / "default")


@pytest.fixture(scope="module")
def short_run(tmp_path_factory: pytest.TempPathFactory):  # noqa: ANN201
    """A 1 s run of the default scenario, for tests that read it or copy its folder."""
    folder = tmp_path_factory.mktemp("short")
    return run(scenario(folder, "short", ("duration = 10.0", "duration = 1.0")), folder / "run")


def hil_estimate(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, list[str]]:
    from hil.cli import main

    code = main(["estimate", *argv])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return code, err.splitlines()


@pytest.fixture(scope="module")
def ideal_run(tmp_path_factory: pytest.TempPathFactory):  # noqa: ANN201
    folder = tmp_path_factory.mktemp("ideal")
    return run(scenario(folder, "ideal", *IDEAL), folder / "ideal")


def test_the_default_camera_is_realistic(default_run) -> None:  # noqa: ANN001
    s = load_scenario(DEFAULT_SCENARIO)
    assert (s.camera.noise, s.camera.dropout, s.camera.outlier_rate) == (0.5e-3, 0.01, 0.001)
    assert s.controller.estimator == "ukf"
    # dropouts reached the bus: some pictures hold fewer markers than the arm has
    log = (default_run.out / "can.log").read_text().splitlines()
    headers = [line for line in log if " 27F#" in line]
    markers = [int(line.split("#")[1][10:12], 16) for line in headers]
    assert len(headers) == 1000 and 0 < markers.count(1) < 60 and markers.count(2) > 900


def test_chosen_estimator_halves_raw_error_and_tracks_like_an_ideal_camera(
    default_run,  # noqa: ANN001
    ideal_run,  # noqa: ANN001
) -> None:
    estimation = default_run.summary["estimation"]
    assert set(estimation) == {"chosen", "raw", "kf", "ukf"}
    for name in ("raw", "kf", "ukf"):
        assert set(estimation[name]) == {"rms", "max", "gated", "update_time"}
    chosen = estimation[estimation["chosen"]]
    assert chosen["rms"] <= 0.5 * estimation["raw"]["rms"]
    # the chosen default is the better of the two filters on this scenario
    assert estimation["ukf"]["rms"] <= estimation["kf"]["rms"]
    assert (
        default_run.summary["rms_tracking_error"] <= 1.1 * ideal_run.summary["rms_tracking_error"]
    )
    # the controller's own estimate (reported on the bus) agrees with the offline ukf
    signals = read_signals(default_run.out / "signals.csv")
    error = (signals["kappa_est_1"] - signals["kappa_1"])[1:-1]
    assert np.sqrt(np.mean(error**2)) == pytest.approx(chosen["rms"], rel=0.05)
    assert (default_run.out / "estimation.png").stat().st_size > 10_000


def test_dropouts_and_occlusions_keep_the_loop_stable(
    tmp_path: Path,
    ideal_run,  # noqa: ANN001
) -> None:
    path = scenario(
        tmp_path,
        "occluded",
        ("dropout = 0.01", "dropout = 0.2\nocclusion_interval = 2.0\nocclusion_duration = 0.2"),
    )
    result = run(path, tmp_path / "occluded")
    assert result.summary["status"] == "completed"
    assert result.summary["rms_tracking_error"] <= 2.0 * ideal_run.summary["rms_tracking_error"]
    signals = read_signals(result.out / "signals.csv")
    assert np.nanmax(np.abs(signals["kappa_1"])) < 12.0  # no divergence: the task's peak is 10


def test_a_jittered_camera_keeps_the_loop_running(tmp_path: Path) -> None:
    """Exposure jitter delays a picture up to a frame period less one tick: the controller waits
    for each frame by the SYNC its latest exposure allows (before, the strict policy waited 10 s
    for a frame the camera had not taken yet, then stopped the run), every frame is used, the
    loop tracks as without jitter, and the run is the same across processes."""
    short = ("duration = 10.0", "duration = 1.0")
    path = scenario(tmp_path, "jittered", short, ("dropout = 0.01", "jitter = 0.004"))
    result = run(path, tmp_path / "jittered")
    assert result.summary["status"] == "completed"
    config = json.loads((result.out / "controller.json").read_text())
    assert config["camera_timing"]["delay_ticks"] == 9  # 100 Hz camera, 1 ms steps
    report = result.summary["controller"]
    # frames exposed by t = 1 s - (6 ms latency + 9 ms delay): 0 .. 98
    assert report["camera_frames"] + report["camera_frames_incomplete"] == 99
    assert report["camera_frames"] >= 90
    steady = run(scenario(tmp_path, "steady", short), tmp_path / "steady")
    assert (
        json.loads((steady.out / "controller.json").read_text())["camera_timing"]["delay_ticks"]
        == 0
    )
    error = result.summary["rms_tracking_error"]
    assert error == pytest.approx(steady.summary["rms_tracking_error"], rel=0.02)
    process = run(path, tmp_path / "process", process=True)
    assert (process.out / "can.log").read_bytes() == (result.out / "can.log").read_bytes()


def test_outliers_never_make_an_estimate_jump(tmp_path: Path) -> None:
    path = scenario(tmp_path, "outliers", ("outlier_rate = 0.001", "outlier_rate = 0.01"))
    result = run(path, tmp_path / "outliers")
    config = config_beside(result.out / "can.log")
    cycles = measured_cycles(result.out / "can.log", config)
    truth = read_signals(result.out / "signals.csv")["kappa_1"]
    outliers = 0
    for name in ("kf", "ukf"):
        s = score(name, config, cycles)
        outliers = int(s.gated.sum())
        error = np.abs(s.kappa[1:, 0] - truth[1:])
        # no estimate strays by more than 5 of its own standard deviations
        assert np.all(error <= 5.0 * s.kappa_std[1:, 0]), name
    assert outliers > 10  # ~1 % of 2 markers x 1000 pictures were rejected


def test_latency_compensation_measurably_helps(tmp_path: Path) -> None:
    """A loop fast enough for 10 ms to matter (3 Hz crossover): without compensation the
    estimate is a period late and noisier, and the curvature tracks worse."""
    results = {}
    for flag in ("true", "false"):
        path = scenario(
            tmp_path,
            f"latency-{flag}",
            ("crossover = 1.0", "crossover = 3.0"),
            ("latency_compensation = true", f"latency_compensation = {flag}"),
        )
        results[flag] = run(path, tmp_path / flag).summary
    on, off = results["true"], results["false"]
    assert off["estimation"]["ukf"]["rms"] > 1.5 * on["estimation"]["ukf"]["rms"]
    assert off["rms_tracking_error"] > on["rms_tracking_error"]
    holds = [
        np.mean([h["steady_state_error"] for h in r["segments"][0]["steps"]]) for r in (on, off)
    ]
    assert holds[1] > holds[0]


@pytest.mark.parametrize(
    ("estimator", "transport"),
    # each estimator's separate-process run takes another transport: the binary records on
    # hil run's own hub (hosted by the plant: the default; or a child process), the binary
    # records on a hub thread of the plant, socketcand's ASCII on an external hub
    [
        ("raw", "socketcand"),
        ("kf", "binary-thread-hub"),
        ("ukf", "binary"),
        ("ukf", "binary-hub-process"),
    ],
)
def test_every_estimator_is_deterministic_in_process_and_across_processes(
    tmp_path: Path, estimator: str, transport: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = scenario(
        tmp_path,
        estimator,
        ('estimator = "ukf"', f'estimator = "{estimator}"'),
        ("duration = 10.0", "duration = 1.0"),
    )
    first = run(path, tmp_path / "a")
    again = run(path, tmp_path / "b")
    with contextlib.ExitStack() as stack:
        bus = None
        if transport == "socketcand":
            hub = stack.enter_context(LoopbackHub())
            bus = f"loopback:127.0.0.1:{hub.port}"
        elif transport == "binary-thread-hub":
            monkeypatch.setenv("SOFTHIL_HUB", "thread")
        elif transport == "binary-hub-process":
            monkeypatch.setenv("SOFTHIL_HUB", "process")
        else:
            monkeypatch.delenv("SOFTHIL_HUB", raising=False)  # the default: the plant hosts it
            # and both processes busy-poll (on by default with two cores or more)
            monkeypatch.setenv("SOFTHIL_BUSY_POLL", "0.001")
        other = run(path, tmp_path / "c", process=True, bus=bus)
    assert other.summary["bus"].startswith("loopback:" if bus else "softhil:")
    assert other.summary["bus"].endswith(",busy_poll=0.001") == (transport == "binary")
    hubs = {"socketcand": None, "binary-thread-hub": "thread", "binary-hub-process": "process"}
    assert other.summary["hub"] == hubs.get(transport, "plant")  # the plant hosts it by default
    assert first.summary["hub"] is None  # in-process: no hub at all
    for name in ("can.log", "signals.csv"):
        data = (first.out / name).read_bytes()
        assert (again.out / name).read_bytes() == data
        assert (other.out / name).read_bytes() == data
    assert json.loads((first.out / "controller.json").read_text())["estimator"] == estimator


def test_hil_estimate_rescores_a_recorded_run(default_run, tmp_path: Path) -> None:  # noqa: ANN001
    report = estimation_report(default_run.out, plot=False)
    assert report == default_run.summary["estimation"] | {
        name: report[name] | {"update_time": report[name]["update_time"]}
        for name in ("raw", "kf", "ukf")
    }
    for name in ("raw", "kf", "ukf"):
        for key in ("rms", "max", "gated"):
            assert report[name][key] == default_run.summary["estimation"][name][key]


@pytest.mark.parametrize(
    ("edit", "key", "reason"),
    [
        (("noise = 0.0005", "noise = -0.001"), "camera.noise", "negative"),
        (("dropout = 0.01", "dropout = 1.5"), "camera.dropout", "[0, 1]"),
        (("outlier_rate = 0.001", "outlier_rate = -0.1"), "camera.outlier_rate", "[0, 1]"),
        (("latency = 0.006", "latency = 0.0065"), "camera.latency", "integer multiple"),
        (
            ('estimator = "ukf"', 'estimator = "ekf"'),
            "controller.estimator",
            "must be one of raw, kf, ukf",
        ),
        (("noise = 0.0005", "noise = 0.2"), "camera.noise", "field of view"),
        (
            ("dropout = 0.01", 'dropout = 0.01\nocclusion_scope = "half"'),
            "camera.occlusion_scope",
            "",
        ),
        (("dropout = 0.01", "dropout = 0.01\njitter = 0.02"), "camera.jitter", ""),
    ],
)
def test_bad_camera_keys_fail_before_the_run(
    tmp_path: Path, edit: tuple[str, str], key: str, reason: str
) -> None:
    from hil.errors import ScenarioError

    path = scenario(tmp_path, "bad", edit)
    with pytest.raises(ScenarioError) as error:
        load_scenario(path)
    message = str(error.value)
    assert f": {key}: " in message and reason in message and "\n" not in message


def test_estimation_plot_marks_missing_markers_and_measures_only_seen_ones(default_run) -> None:  # noqa: ANN001
    # what estimation.png draws, on pictures made up around a known estimate: a seen marker's
    # residual is its distance from where the estimate puts it; an unseen one has none and marks
    # its segment as missing in that cycle; a cycle without pictures marks nothing
    config = config_beside(default_run.out / "can.log")
    assert config.segments == 1
    kappa = np.array([[0.0], [5.0], [-3.0]])
    placed = [kinematics.markers(k, config.lengths, config.base) for k in kappa]
    off = placed[1].copy()
    off[1] += [3e-3, 4e-3]  # the tip 5 mm from the estimate
    hidden = placed[2].copy()
    hidden[1] = np.nan
    cycles = [
        (0.0, {}, []),
        (0.01, {}, [MarkerFrame(0.004, off)]),
        (0.02, {}, [MarkerFrame(0.014, hidden)]),
    ]
    missing, t, residual = marker_residuals(cycles, kappa, config)
    assert missing.tolist() == [[False], [False], [True]]
    assert t.tolist() == [0.01, 0.01, 0.02]
    assert residual == pytest.approx([0.0, 5.0, 0.0], abs=1e-9)


def test_the_report_scored_in_a_child_process_is_the_same(tmp_path: Path) -> None:
    # `hil run` scores the estimators in a forked child while it draws the plots: the same
    # report and the same estimation.png as scored in turn (only the timings differ)
    path = scenario(tmp_path, "short", ("duration = 10.0", "duration = 1.0"))
    runs = {}
    for parallel in (False, True):
        options = RunOptions(
            out=tmp_path / f"parallel-{parallel}", inprocess=True, progress=False,
            parallel_report=parallel,
        )  # fmt: skip
        runs[parallel] = run_scenario(load_scenario(path), options)

    def scores(result) -> dict:  # noqa: ANN001
        report = result.summary["estimation"]
        return {k: v if isinstance(v, str) else v | {"update_time": 0} for k, v in report.items()}

    assert scores(runs[True]) == scores(runs[False])
    assert set(scores(runs[True])) == {"chosen", "raw", "kf", "ukf"}
    png = [(r.out / "estimation.png").read_bytes() for r in runs.values()]
    assert png[0] == png[1]


def test_no_reports_writes_the_run_s_own_files_the_same_and_draws_nothing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """`hil run --no-reports`: the same CAN log, signals and summary (but its estimation
    scores), no plot, figure or estimation report; the line naming the results says so."""
    from hil.cli import main

    path = scenario(tmp_path, "short", ("duration = 10.0", "duration = 0.5"))
    drawn = run_scenario(
        load_scenario(path), RunOptions(out=tmp_path / "drawn", inprocess=True, progress=False)
    )
    bare = tmp_path / "bare"
    argv = ["run", str(path), "--inprocess", "--no-progress", "--no-reports", "--out", str(bare)]
    assert main(argv) == 0
    assert sorted(p.name for p in drawn.out.glob("*.png")) == [
        "curvature.png", "estimation.png", "piston.png", "pressures.png"
    ]  # fmt: skip
    assert list(bare.glob("*.png")) == []
    for name in ("can.log", "signals.csv"):
        assert (bare / name).read_bytes() == (drawn.out / name).read_bytes(), name
    summary = json.loads((bare / "summary.json").read_text())
    timing = {"wall_time", "real_time_factor", "startup_time", "controller", "plant"}
    timing.add("periods_on_kernel_thread")  # the CLI steps ahead on a spare core
    assert "estimation" not in summary and "estimation" in drawn.summary
    assert {k: v for k, v in summary.items() if k not in timing} == {
        k: v for k, v in drawn.summary.items() if k not in timing | {"estimation"}
    }
    out = capsys.readouterr().out
    assert f"results in {bare}/ (signals.csv, can.log, summary.json)" in out


@pytest.mark.parametrize("parallel", [False, True])
def test_a_run_without_a_readable_log_reports_why_in_either_way(
    tmp_path: Path, parallel: bool
) -> None:
    from hil.run import _estimation_report

    with _estimation_report(tmp_path, parallel) as estimation:
        scores, error = estimation()
    assert scores is None and error is not None and "no CAN log" in error


def _report_in(folder: Path) -> tuple[object, object]:
    from hil.run import _estimation_report

    with _estimation_report(folder, True) as estimation:
        return estimation()


def test_a_daemon_process_scores_in_turn(tmp_path: Path) -> None:
    # a daemonic process (a multiprocessing.Pool worker running `hil run`) may not start the
    # child: it scores the estimators itself instead of failing
    import multiprocessing

    with multiprocessing.get_context("fork").Pool(1) as pool:
        scores, error = pool.apply(_report_in, (tmp_path,))
    assert scores is None and "no CAN log" in str(error)


@pytest.mark.parametrize("parallel", [False, True])
def test_a_failed_report_is_a_warning_and_the_run_stands(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, parallel: bool
) -> None:
    import hil.estimation
    from hil.errors import HilError

    def unreadable(out: Path, plot: bool = True, log: Path | None = None) -> dict:
        raise HilError(f"{out.name}/can.log: made unreadable")

    monkeypatch.setattr(hil.estimation, "estimation_report", unreadable)
    path = scenario(tmp_path, "short", ("duration = 10.0", "duration = 0.5"))
    options = RunOptions(
        out=tmp_path / "run", inprocess=True, progress=False, parallel_report=parallel
    )
    s = run_scenario(load_scenario(path), options).summary
    assert s["status"] == "completed"
    assert s["estimation"] == {"error": "run/can.log: made unreadable"}
    assert "no estimation report: run/can.log: made unreadable" in s["warnings"]


def test_hil_estimate_of_a_file_names_its_folder(
    short_run, capsys: pytest.CaptureFixture[str]
) -> None:  # noqa: ANN001
    log = short_run.out / "can.log"
    code, lines = hil_estimate(capsys, str(log))
    assert code == 1 and lines == [
        f"hil: error: {log}: is a file; give the results folder of a run ({short_run.out})"
    ]


@pytest.mark.parametrize("name", ["estimation.json", "estimation.png"])
def test_hil_estimate_into_a_folder_in_the_way_is_one_line(
    short_run, tmp_path: Path, capsys: pytest.CaptureFixture[str], name: str
) -> None:  # noqa: ANN001
    import shutil

    folder = tmp_path / "run"
    shutil.copytree(short_run.out, folder)
    (folder / name).unlink(missing_ok=True)
    (folder / name).mkdir()
    code, lines = hil_estimate(capsys, str(folder))
    assert code == 1 and len(lines) == 1
    assert lines[0].startswith(f"hil: error: {folder / name}: cannot write: ")


def test_hil_estimate_waits_for_no_run_writing_in_the_folder(
    short_run, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:  # noqa: ANN001
    """A run (or another hil estimate) holding the folder's lock: refused in one line, nothing
    written; a lock left by a process that is gone is taken over with a note."""
    import os
    import shutil

    import hil.results

    folder = tmp_path / "run"
    shutil.copytree(short_run.out, folder)
    (folder / "estimation.json").unlink(missing_ok=True)
    lock = folder / hil.results.LOCK
    lock.write_text(f"{os.getppid()}\n")  # a live process holds it
    manifest = (folder / hil.results.MANIFEST).read_bytes()
    code, lines = hil_estimate(capsys, str(folder), "--no-plot")
    assert code == 1 and len(lines) == 1 and "is in use by another run" in lines[0]
    assert not (folder / "estimation.json").exists()
    assert (folder / hil.results.MANIFEST).read_bytes() == manifest
    lock.write_text("999999999\n")  # gone
    code, lines = hil_estimate(capsys, str(folder), "--no-plot")
    assert code == 0 and len(lines) == 1 and "took over the stale lock" in lines[0]
    assert (folder / "estimation.json").is_file() and not lock.exists()


@pytest.mark.parametrize("can_log", ["run.log", "trace.blf"])
def test_the_report_reads_the_can_log_by_the_name_the_run_gave_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], can_log: str
) -> None:
    path = scenario(tmp_path, "short", ("duration = 10.0", "duration = 1.0"))
    options = RunOptions(out=tmp_path / "run", inprocess=True, progress=False, can_log=can_log)
    s = run_scenario(load_scenario(path), options).summary
    assert not [w for w in s["warnings"] if "estimation" in w]
    assert set(s["estimation"]) == {"chosen", "raw", "kf", "ukf"}
    code, lines = hil_estimate(capsys, str(tmp_path / "run"), "--no-plot")
    assert code == 0 and not lines
    again = json.loads((tmp_path / "run" / "estimation.json").read_text())
    assert again["kf"]["rms"] == s["estimation"]["kf"]["rms"]


def test_a_rerun_with_overwrite_replaces_what_hil_estimate_wrote(
    short_run, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:  # noqa: ANN001
    import shutil

    folder = tmp_path / "run"
    shutil.copytree(short_run.out, folder)
    assert hil_estimate(capsys, str(folder)) == (0, [])
    assert (folder / "estimation.json").is_file()
    (folder / "notes.txt").write_text("mine\n")
    path = scenario(tmp_path, "short", ("duration = 10.0", "duration = 0.3"))
    options = RunOptions(out=folder, inprocess=True, progress=False, overwrite=True)
    run_scenario(load_scenario(path, seed=3), options)
    assert not (folder / "estimation.json").exists()  # the earlier run's report is gone
    assert (folder / "notes.txt").read_text() == "mine\n"
    assert json.loads((folder / "summary.json").read_text())["seed"] == 3


@pytest.mark.parametrize("said_by", ["scenario.toml", "controller.json"])
def test_hil_estimate_of_a_fish_run_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], said_by: str
) -> None:
    # without its scenario.toml, the run's controller.json says it is a fish
    from hil.scenario import resolve_scenario

    text = resolve_scenario("fish-escape").read_text()
    path = tmp_path / "fish.toml"
    path.write_text(text.replace("duration = 0.4", "duration = 0.1"))
    assert "duration = 0.1" in path.read_text()
    folder = tmp_path / "run"
    run(path, folder)
    if said_by == "controller.json":
        (folder / "scenario.toml").unlink()
    code, lines = hil_estimate(capsys, str(folder))
    assert code == 1 and len(lines) == 1
    assert "estimation report applies to planar-arm runs" in lines[0] and "'fish'" in lines[0]
    assert lines[0].endswith(f"({said_by})")
    assert not (folder / "estimation.json").exists()


def _untouched(folder: Path) -> tuple[bytes, list[str]]:
    """What `hil estimate` must leave as it was when it refuses: the manifest, the file list."""
    import hil.results

    return (folder / hil.results.MANIFEST).read_bytes(), sorted(p.name for p in folder.iterdir())


def test_hil_estimate_refuses_a_csv_can_log_before_writing(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    # a CSV log has no direction: no plant frame is found and every estimator scored nothing,
    # so it is refused as `hil replay` refuses it, with nothing written
    path = scenario(tmp_path, "short", ("duration = 10.0", "duration = 0.3"))
    options = RunOptions(out=tmp_path / "run", inprocess=True, progress=False, can_log="can.csv")
    run_scenario(load_scenario(path), options)
    folder = tmp_path / "run"
    before = _untouched(folder)
    code, lines = hil_estimate(capsys, str(folder))
    assert code == 1 and lines == [
        f"hil: error: {folder / 'can.csv'}: hil estimate cannot use a .csv log: python-can's CSV "
        "has no direction column, so the controller's frames cannot be told from the plant's "
        "(record with --can-log can.log, .asc, .blf or .trc)"
    ]
    assert _untouched(folder) == before


def _cut_mid_line(signals: Path) -> None:
    """Cut after the third cell of line 50 (a copy interrupted half-way)."""
    lines = signals.read_text().split("\n")
    signals.write_text("\n".join([*lines[:49], ",".join(lines[49].split(",")[:3])]))


def _cut_in_the_last_cell(signals: Path) -> None:
    text = signals.read_text()
    signals.write_text(text[:-3])


def _not_a_number(signals: Path) -> None:
    lines = signals.read_text().split("\n")
    cells = lines[5].split(",")
    cells[3] = "abc"
    lines[5] = ",".join(cells)
    signals.write_text("\n".join(lines))


@pytest.mark.parametrize(
    ("damage", "expected"),
    [
        (
            lambda s: s.unlink(),
            "{signals}: no such file (its blocks are in signals.parquet: hil csv {folder})",
        ),
        (
            _cut_mid_line,
            "{signals}: line 50: 3 cells where the header names 12 (a file cut short?)",
        ),
        (
            _cut_in_the_last_cell,
            "{signals}: line {last}: cut short (the last line has no line end)",
        ),
        (_not_a_number, "{signals}: line 6, column kappa_1: 'abc' is not a number"),
        (lambda s: s.write_text(""), "{signals}: empty: no header line of signal names"),
        (
            lambda s: (s.parent / "controller.json").unlink(),
            "{folder}/controller.json: no controller.json beside the log; hil estimate needs the "
            "run's controller configuration (estimator, camera, arm) to rebuild what its "
            "estimator was given",
        ),
    ],
    ids=["no-signals", "cut-mid-line", "cut-in-last-cell", "not-a-number", "empty", "no-config"],
)
def test_hil_estimate_of_a_damaged_folder_is_one_line_naming_the_file(
    short_run, tmp_path: Path, capsys: pytest.CaptureFixture[str], damage, expected: str
) -> None:  # noqa: ANN001
    import shutil

    folder = tmp_path / "run"
    shutil.copytree(short_run.out, folder)
    (folder / "estimation.json").unlink(missing_ok=True)
    signals = folder / "signals.csv"
    rows = signals.read_text().count("\n")  # the header and one line a cycle
    assert rows > 50
    damage(signals)
    before = _untouched(folder)
    code, lines = hil_estimate(capsys, str(folder))
    assert code == 1 and lines == [
        f"hil: error: {expected.format(signals=signals, folder=folder, last=rows)}"
    ]
    assert _untouched(folder) == before  # nothing written, not even the manifest


def test_hil_estimate_of_a_read_only_folder_says_so(
    short_run, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:  # noqa: ANN001
    import errno
    import os
    import shutil

    import hil.results

    folder = tmp_path / "run"
    shutil.copytree(short_run.out, folder)
    (folder / "estimation.json").unlink(missing_ok=True)
    before = _untouched(folder)
    real_open = os.open

    def read_only(path, flags, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        if flags & (os.O_WRONLY | os.O_RDWR) and Path(path).parent == folder:
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(path))
        return real_open(path, flags, *args, **kwargs)

    monkeypatch.setattr(hil.results.os, "open", read_only)
    for argv, files in (
        ((), "estimation.json and estimation.png"),
        (("--no-plot",), "estimation.json"),
    ):
        code, lines = hil_estimate(capsys, str(folder), *argv)
        assert code == 1 and lines == [
            f"hil: error: results folder {folder} is read-only ({os.strerror(errno.EROFS)}): "
            f"hil estimate writes {files} there; copy the folder somewhere writable"
        ]
    assert _untouched(folder) == before


def test_hil_estimate_says_whose_controller_ran(
    short_run, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:  # noqa: ANN001
    """A run under a user's program used the program's own estimator, not controller.json's."""
    import shutil

    from hil.cli import main

    folder = tmp_path / "run"
    shutil.copytree(short_run.out, folder)
    said = {}
    for program in ("softhil", "external", "python mine.py --bus {bus}", None):
        summary = json.loads((folder / "summary.json").read_text())
        summary["controller_program"] = program
        (folder / "summary.json").write_text(json.dumps(summary))
        assert main(["estimate", str(folder), "--no-plot"]) == 0
        said[program] = capsys.readouterr().out.splitlines()[0].partition(" (")[2]
    assert said == {
        "softhil": "controller used ukf)",
        None: "controller used ukf)",  # a run before softhil recorded who
        "external": "the run's controller was an external controller; softhil's would use ukf)",
        "python mine.py --bus {bus}": "the run's controller was your program; softhil's would "
        "use ukf)",
    }
