"""Batches and sweeps: many seeded runs of one scenario, on local worker processes or on Dask.

A batch runs one scenario with N consecutive seeds; a sweep runs every point of a grid of
`--set section.key=v1,v2,...` overrides, each with N seeds. Every trial is a plain picklable
`TrialSpec` carrying its whole scenario TOML text, and runs in a worker through `run_trial`
(in-process mode: plant and controller in one thread, byte-identical to the process mode), which
never raises: a failing trial comes back with its status and error, and the others go on. Each
trial keeps its own run folder (`scenario.toml` as it ran, `summary.json`, logs, plots).

Invariant: `batch.json` depends only on the scenario, the seeds and the overrides, never on the
executor, the number of workers, the order in which trials finish or the wall clock (trials are
ordered by index, keys sorted, folders relative, wall times kept apart in `timing.json`); so a
batch run twice, or locally and on a Dask cluster, writes the same bytes.
"""

from __future__ import annotations

import contextlib
import datetime
import hashlib
import io
import itertools
import json
import math
import multiprocessing
import os
import re
import signal
import socket
import statistics
import sys
import tempfile
import threading
import time
import tomllib
from collections.abc import Callable, Iterable, Mapping, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, as_completed, wait
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from hil.environment import KERNEL_THREAD
from hil.errors import HilError, ScenarioError, Terminated
from hil.program import SOFTHIL, check_controller
from hil.results import ResultsFolder, note, write_file
from hil.run import RunOptions, run_scenario
from hil.scenario import Scenario, load_scenario

# the top-level keys of a scenario; a --set key starting with anything else names a robot key
SECTIONS = frozenset(f.name for f in fields(Scenario) if f.name != "source")
# summary.json values that measure the machine, not the run (two runs of one scenario differ
# only in these: found by diffing the summaries of two identical runs); any later key naming
# the wall clock is caught by WALL_CLOCK_WORDS
# (periods_on_kernel_thread: the run chooses the thread by timing its first periods)
WALL_CLOCK_KEYS = frozenset(
    {"wall_time", "real_time_factor", "startup_time", "periods_on_kernel_thread"}
)
WALL_CLOCK_WORDS = ("wall", "real_time", "startup", "lateness", "overrun")
# summary.json values that echo the scenario's inputs rather than measure the run
INPUT_KEYS = frozenset({"seed", "duration", "bitrate", "log_start"})
OUTPUT_FILES = ("batch.json", "timing.json", "batch.png")
MAX_TRIALS = 10_000  # in one batch or sweep: each is a folder of results and a worker's run
CHECK_NOTE_POINTS = 50  # a grid larger than this says that it is being checked
# a bare word on the command line (kf, ukf, frame) is taken as a string: the shell eats quotes
_BARE_WORD = re.compile(r"[A-Za-z_][A-Za-z0-9_-]*")
_BARE_KEY = re.compile(r"[A-Za-z0-9_-]+")
# pyplot (the run's plots) is not thread-safe: one trial at a time per worker process, so that a
# Dask worker started with several threads stays correct (it then runs them one after another)
_RUN_LOCK = threading.Lock()


@dataclass(frozen=True)
class Override:
    """One `--set` option: a dotted TOML path in the scenario and the values it takes."""

    option: str  # as given on the command line, for errors
    key: str  # the dotted path in the scenario file (robot keys completed with "robot.")
    values: tuple[Any, ...]


@dataclass(frozen=True)
class TrialSpec:
    """One trial, complete and picklable: what a worker needs to run it anywhere."""

    index: int  # position in the batch; results are ordered by it
    seed: int
    point: int  # grid point of a sweep (0 in a batch)
    overrides: tuple[tuple[str, Any], ...]  # (dotted key, value) of its grid point
    folder: str  # absolute path of the trial's run folder
    name: str  # the folder's name relative to the batch folder
    scenario_text: str  # the scenario.toml the trial runs, with its seed and overrides
    # the controller program (hil.program): softhil's, in the trial's own process, or a user's
    # command line, a process of its own beside it
    controller: str = SOFTHIL


@dataclass(frozen=True)
class Plan:
    """A checked batch or sweep: every trial's scenario loads, nothing has run yet."""

    kind: str  # "batch" or "sweep"
    command: str  # the options that determine the results (not --out, --workers, --scheduler)
    scenario: str  # the scenario's name
    source_sha256: str  # of the scenario file's bytes
    out: Path
    overrides: tuple[Override, ...]
    points: tuple[tuple[tuple[str, Any], ...], ...]  # the grid, cartesian product of overrides
    seeds: tuple[int, ...]  # of every grid point
    trials: tuple[TrialSpec, ...]


# ------------------------------------------------------------------ --set options


def parse_set(option: str) -> Override:
    """`section.key=v1,v2,...` to an Override; values are TOML (numbers, booleans, quoted
    strings, arrays), a bare word is a string. A key whose first part is not a top-level key of
    the scenario names a key of its robot (`valve.open_time` is `robot.valve.open_time`)."""
    key, sep, text = option.partition("=")
    key = key.strip()
    if not sep or not key or not text.strip():
        raise HilError(f"--set {option}: expected section.key=value[,value...]")
    parts = key.split(".")
    if not all(_BARE_KEY.fullmatch(p) for p in parts):
        raise HilError(f"--set {option}: {key!r} is not a dotted TOML key (section.key)")
    if parts[0] in ("seed", "source"):
        raise HilError(f"--set {option}: {parts[0]} is not a swept key; use --seed and --trials")
    if parts[0] not in SECTIONS:
        parts = ["robot", *parts]
    values = _values(option, text)
    if len(set(map(_same, values))) != len(values):
        raise HilError(f"--set {option}: a value is repeated")
    return Override(option, ".".join(parts), tuple(values))


def _values(option: str, text: str) -> list[Any]:
    try:
        values = list(tomllib.loads(f"v = [{text}]")["v"])
        if not any(_dated(v) for v in values):
            return values
    except tomllib.TOMLDecodeError:
        pass
    values = []
    for item in (part.strip() for part in text.split(",")):
        if _BARE_WORD.fullmatch(item) and item not in ("true", "false", "inf", "nan"):
            values.append(item)
            continue
        try:
            value = tomllib.loads(f"v = {item}")["v"]
            # a bare date is a bare word too: the string as typed (a scenario takes instants
            # as strings, and batch.json has no dates)
            values.append(item if _dated(value) is True else _undated(value))
        except tomllib.TOMLDecodeError:
            raise HilError(
                f"--set {option}: {item!r} is not a TOML value (a number, true/false, a quoted "
                "string or an array)"
            ) from None
    return values


def _dated(value: Any) -> bool | str:
    """True for a TOML date or time, "inside" for a table or array holding one, else False."""
    if isinstance(value, datetime.date | datetime.time):
        return True
    if isinstance(value, list):
        return "inside" if any(_dated(v) for v in value) else False
    if isinstance(value, dict):
        return "inside" if any(_dated(v) for v in value.values()) else False
    return False


def _undated(value: Any) -> Any:
    """`value` with each date or time inside it as its ISO 8601 string."""
    if isinstance(value, datetime.date | datetime.time):
        return value.isoformat().replace("+00:00", "Z")
    if isinstance(value, list):
        return [_undated(v) for v in value]
    if isinstance(value, dict):
        return {k: _undated(v) for k, v in value.items()}
    return value


def _canonical(value: Any) -> str:
    return json.dumps(value, sort_keys=True)


def _same(value: Any) -> str:
    """Equal values give equal keys: 1 and 1.0 are one value (the scenario reads both as 1.0)."""

    def numbers(v: Any) -> Any:
        if isinstance(v, int) and not isinstance(v, bool):
            return float(v)
        if isinstance(v, list):
            return [numbers(x) for x in v]
        if isinstance(v, dict):
            return {k: numbers(x) for k, x in v.items()}
        return v

    return json.dumps(numbers(value), sort_keys=True)


def apply_overrides(data: Mapping[str, Any], overrides: Iterable[tuple[str, Any]]) -> dict:
    """A deep copy of the parsed scenario with each dotted key set; missing tables are created
    (the scenario's own checks then judge the key)."""
    result = json.loads(json.dumps(data))  # a deep copy; scenario TOML holds no dates
    for key, value in overrides:
        table = result
        parts = key.split(".")
        for depth, part in enumerate(parts[:-1]):
            table = table.setdefault(part, {})
            if not isinstance(table, dict):
                raise HilError(f"{key}: {'.'.join(parts[: depth + 1])} is not a table")
        table[parts[-1]] = value
    return result


# ------------------------------------------------------------------ a small TOML writer


def dumps_toml(data: Mapping[str, Any]) -> str:
    """TOML text of a parsed scenario (tables, arrays of tables, inline arrays and tables,
    strings, numbers, booleans); `tomllib.loads(dumps_toml(d)) == d`. Floats keep every digit
    (repr), so a trial runs exactly the value it was given."""
    lines: list[str] = []
    _table(data, [], lines)
    return "\n".join(lines).lstrip("\n") + "\n"


def _table(data: Mapping[str, Any], path: list[str], lines: list[str]) -> None:
    tables = {k: v for k, v in data.items() if isinstance(v, dict)}
    arrays = {k: v for k, v in data.items() if _array_of_tables(v)}
    for key, value in data.items():
        if key not in tables and key not in arrays:
            lines.append(f"{_key(key)} = {_value(value)}")
    for key, value in tables.items():
        lines.extend(["", f"[{'.'.join(_key(p) for p in [*path, key])}]"])
        _table(value, [*path, key], lines)
    for key, items in arrays.items():
        for item in items:  # a sub-table header after [[a]] belongs to that element
            lines.extend(["", f"[[{'.'.join(_key(p) for p in [*path, key])}]]"])
            _table(item, [*path, key], lines)


def _array_of_tables(value: Any) -> bool:
    return isinstance(value, list) and bool(value) and all(isinstance(v, dict) for v in value)


def _key(key: str) -> str:
    return key if _BARE_KEY.fullmatch(key) else _string(key)


def _string(text: str) -> str:
    # JSON's escapes are TOML's, except that TOML wants DEL escaped too
    return json.dumps(text, ensure_ascii=False).replace("\x7f", "\\u007f")


def _value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if math.isnan(value):
            return "nan"
        if math.isinf(value):
            return "inf" if value > 0 else "-inf"
        return repr(value)
    if isinstance(value, str):
        return _string(value)
    if isinstance(value, list):
        return "[" + ", ".join(_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{ " + ", ".join(f"{_key(k)} = {_value(v)}" for k, v in value.items()) + " }"
    raise HilError(f"cannot write {value!r} as TOML")  # dates: scenarios hold none


# ------------------------------------------------------------------ planning


def make_plan(
    source: Path,
    *,
    kind: str,
    command: str,
    out: Path | None,
    trials: int,
    seed: int | None = None,
    overrides: Sequence[Override] = (),
    controller: str = SOFTHIL,
) -> Plan:
    """Every trial of a batch (no overrides) or sweep, checked before anything runs: each value
    of each --set option, then each grid point, loads as a scenario, or a one-line error names
    the option."""
    if trials < 1:
        raise HilError(f"--trials: must be at least 1, got {trials}")
    points_count = math.prod(len(o.values) for o in overrides)
    if points_count * trials > MAX_TRIALS:
        split = "split it: fewer values, or --seed and --trials in parts"
        if overrides:
            raise HilError(
                f"--set: {points_count} grid points x {count(trials, 'trial')} = "
                f"{points_count * trials} trials; at most {MAX_TRIALS} in one batch or sweep "
                f"({split})"
            )
        raise HilError(f"--trials: {trials} trials; at most {MAX_TRIALS} in one batch ({split})")
    check_controller(controller, external=False, what="a batch")
    keys = [o.key for o in overrides]
    for key in keys:
        if keys.count(key) > 1:
            raise HilError(f"--set {key}: given twice; list its values once (a,b,c)")
    base = load_scenario(source, seed=seed)
    raw = source.read_bytes()
    data = _anchored(tomllib.loads(raw.decode("utf-8")), source)
    first = base.seed
    seeds = tuple(range(first, first + trials))
    with tempfile.TemporaryDirectory(prefix="softhil-set-") as scratch:
        for override in overrides:  # one value at a time: the error names its option
            for value in override.values:
                try:
                    _check(data, ((override.key, value),), first, Path(scratch), override.option)
                except ScenarioError as exc:
                    raise _hinted(exc, override) from None
        points = tuple(
            tuple(zip(keys, combination, strict=True))
            for combination in itertools.product(*(o.values for o in overrides))
        )
        if len(overrides) > 1:
            if len(points) > CHECK_NOTE_POINTS:  # tens of milliseconds each
                note(f"checking {len(points)} grid points before anything runs")
            for point in points:
                label = " ".join(f"{k}={_canonical(v)}" for k, v in point)
                _check(data, point, first, Path(scratch), label)
    out = out if out is not None else Path("runs") / f"{base.name}-{kind}-{first}"
    total = len(points) * trials
    width = max(3, len(str(total - 1)))
    specs = []
    for p, point in enumerate(points):
        for t, trial_seed in enumerate(seeds):
            index = p * trials + t
            name = f"trial-{index:0{width}d}"
            specs.append(
                TrialSpec(
                    index=index,
                    seed=trial_seed,
                    point=p,
                    overrides=point,
                    folder=str((out / name).absolute()),
                    name=name,
                    scenario_text=_trial_text(data, point, trial_seed, index, kind, source),
                    controller=controller,
                )
            )
    return Plan(
        kind=kind,
        command=command,
        scenario=base.name,
        source_sha256=hashlib.sha256(raw).hexdigest(),
        out=out,
        overrides=tuple(overrides),
        points=points,
        seeds=seeds,
        trials=tuple(specs),
    )


def count(n: int, noun: str) -> str:
    """'1 trial', '2 trials'."""
    return f"{n} {noun}" if n == 1 else f"{n} {noun}s"


def _hinted(exc: ScenarioError, override: Override) -> ScenarioError:
    """An unknown key that --set took for a [robot] key (its first part is no section) says
    that it is no section either: `camra.noise` is a typo of `camera`, not a robot key."""
    first = override.option.partition("=")[0].strip().split(".")[0]
    if override.key.startswith(f"robot.{first}") and f"robot.{first}: unknown key" in str(exc):
        known = ", ".join(sorted(SECTIONS - {"robot", "seed"}))
        return ScenarioError(f"{exc}; {first} is not a top-level key either ({known})")
    return exc


def _anchored(data: dict, source: Path) -> dict:
    """.fmu paths are relative to the scenario file: make them absolute, since a trial's
    scenario.toml lives in its own folder."""

    def walk(value: Any) -> Any:
        if isinstance(value, dict):
            return {k: walk(v) for k, v in value.items()}
        if isinstance(value, list):
            return [walk(v) for v in value]
        if isinstance(value, str) and value.endswith(".fmu") and not Path(value).is_absolute():
            return str((source.parent / value).absolute())
        return value

    return walk(data)  # type: ignore[no-any-return]


def _check(
    data: Mapping[str, Any],
    point: tuple[tuple[str, Any], ...],
    seed: int,
    scratch: Path,
    label: str,
) -> None:
    """Load the scenario with `point` applied; a problem is one line naming `label`."""
    path = scratch / "scenario.toml"
    try:
        text = dumps_toml({**apply_overrides(data, point), "seed": seed})
        path.write_text(text, encoding="utf-8")
        load_scenario(path)
    except HilError as exc:
        reason = str(exc).removeprefix(f"{path}: ")
        raise ScenarioError(f"--set {label}: {reason}") from None


def _trial_text(
    data: Mapping[str, Any],
    point: tuple[tuple[str, Any], ...],
    seed: int,
    index: int,
    kind: str,
    source: Path,
) -> str:
    shown = ", ".join(f"{k} = {_canonical(v)}" for k, v in point) or "none"
    header = (
        f"# hil {kind} trial {index} of scenario {source.name}: seed {seed}, overrides: {shown}\n"
    )
    return header + dumps_toml({**apply_overrides(data, point), "seed": seed})


# ------------------------------------------------------------------ one trial (in a worker)


def run_trial(spec: TrialSpec) -> dict[str, Any]:
    """Run one trial in this process (in-process mode, no progress bar); never raises.

    Returns index, seed, status ("completed" or "failed"), error (None or one line), metrics
    (see `metrics`), success (the summary's boolean, None where the task has none), and the
    machine's side: wall_time [s], host, pid."""
    started = time.perf_counter()
    outcome: dict[str, Any] = {
        "index": spec.index,
        "seed": spec.seed,
        "status": "failed",
        "error": None,
        "metrics": {},
        "success": None,
        "warnings": [],
    }
    try:
        with _RUN_LOCK:
            folder = Path(spec.folder)
            folder.mkdir(parents=True, exist_ok=True)
            path = folder / "scenario.toml"
            write_file(path, spec.scenario_text)
            scenario = load_scenario(path)
            # overwrite: the folder holds only this trial's input (or a retried attempt's files)
            options = RunOptions(
                out=folder,
                inprocess=spec.controller == SOFTHIL,
                progress=False,
                overwrite=True,
                controller=spec.controller,
            )
            run_scenario(scenario, options)
            summary = json.loads((folder / "summary.json").read_text(encoding="utf-8"))
        success = summary.get("success")
        outcome.update(
            status="completed",
            metrics=metrics(summary),
            success=success if isinstance(success, bool) else None,
            warnings=[w for w in summary.get("warnings") or [] if isinstance(w, str)],
        )
    except Exception as exc:  # every failure of a trial is its result, not the batch's end
        outcome["error"] = _one_line(exc)
    outcome.update(
        wall_time=time.perf_counter() - started, host=socket.gethostname(), pid=os.getpid()
    )
    return outcome


def _one_line(exc: BaseException) -> str:
    text = str(exc) if isinstance(exc, HilError) else f"{type(exc).__name__}: {exc}"
    return " ".join(text.split()) or type(exc).__name__


def metrics(summary: Mapping[str, Any]) -> dict[str, float]:
    """The run's deterministic numeric results: top-level int/float values of summary.json
    (not booleans, not nested tables), without the wall-clock ones and the echoed inputs."""
    return {
        key: value
        for key, value in sorted(summary.items())
        if isinstance(value, int | float)
        and not isinstance(value, bool)
        and key not in WALL_CLOCK_KEYS
        and key not in INPUT_KEYS
        and not any(word in key for word in WALL_CLOCK_WORDS)
    }


# ------------------------------------------------------------------ executing


@dataclass(frozen=True)
class Execution:
    """Where trials run: local worker processes, or a Dask scheduler's workers."""

    workers: int | None = None  # local processes; None: os.cpu_count()
    scheduler: str | None = None  # a dask.distributed scheduler address
    progress: bool = True


def execute(
    specs: Sequence[TrialSpec],
    execution: Execution,
    client: Any = None,
    by_index: dict[int, dict[str, Any]] | None = None,
) -> list[dict[str, Any]]:
    """Run every trial, on `client` (a connected dask.distributed Client) if given, else on
    local processes; the outcomes ordered by trial index. A trial whose worker died comes back
    failed like any other; only an interrupt or a lost scheduler ends the whole batch, and then
    `by_index` (trial index -> outcome) holds the trials that finished."""
    from tqdm import tqdm

    by_index = {} if by_index is None else by_index
    with tqdm(
        total=len(specs),
        unit="trial",
        file=sys.stderr,
        disable=None if execution.progress else True,  # None: off where stderr is no TTY
        dynamic_ncols=True,
    ) as bar:

        def done(spec: TrialSpec, outcome: dict[str, Any]) -> None:
            by_index[spec.index] = outcome
            failed = sum(o["status"] != "completed" for o in by_index.values())
            bar.set_postfix(failed=failed, refresh=False)
            bar.update()

        if client is not None:
            _run_dask(specs, client, done)
        else:
            _run_local(specs, execution.workers or os.cpu_count() or 1, done)
    return [by_index[spec.index] for spec in specs]


def _lost(spec: TrialSpec, exc: BaseException) -> dict[str, Any]:
    """The outcome of a trial whose worker did not answer (killed, crashed in an FMU)."""
    return {
        "index": spec.index,
        "seed": spec.seed,
        "status": "failed",
        "error": f"worker lost: {_one_line(exc)}",
        "metrics": {},
        "success": None,
        "wall_time": None,
        "host": None,
        "pid": None,
    }


def _context() -> multiprocessing.context.BaseContext:
    """Workers forked from a fresh server process that has imported softhil once: quick to
    start, and safe even when this process runs threads (a Dask client, a progress bar)."""
    if "forkserver" in multiprocessing.get_all_start_methods():
        context = multiprocessing.get_context("forkserver")
        # the run's plotting and estimation report too: every worker forks warm
        context.set_forkserver_preload(["hil.batch", "hil.plots", "hil.estimation"])
        return context
    return multiprocessing.get_context("spawn")


def _run_local(
    specs: Sequence[TrialSpec],
    workers: int,
    done: Callable[[TrialSpec, dict[str, Any]], None],
) -> None:
    if workers < 1:
        raise HilError(f"--workers: must be at least 1, got {workers}")
    context = _context()
    stopping = context.Event()  # set at an interrupt: a trial queued to a worker never starts
    pool = ProcessPoolExecutor(
        max_workers=min(workers, len(specs)),
        mp_context=context,
        initializer=_worker_start,
        initargs=(stopping, min(workers, len(specs)) > 1),
    )
    futures: dict[Future[dict[str, Any]], TrialSpec] = {}
    reported: set[Future[dict[str, Any]]] = set()
    try:
        futures = {pool.submit(_worker_trial, spec): spec for spec in specs}
        for future in as_completed(futures):
            spec = futures[future]
            try:
                outcome = future.result()
            except Exception as exc:  # BrokenProcessPool: a worker died under this trial
                outcome = _lost(spec, exc)
            reported.add(future)
            done(spec, outcome)
    except BaseException:
        # an interrupt: the trials not started are dropped, those running finish (or stop at
        # a second interrupt, see _stop_pool) and those that finished are reported
        stopping.set()
        try:
            _stop_pool(pool, futures)
        finally:
            for future, spec in futures.items():
                if future not in reported and future.done() and not future.cancelled():
                    try:
                        outcome = future.result()
                    except BaseException:  # noqa: BLE001 - stopped or died: not finished
                        continue
                    done(spec, outcome)
        raise
    pool.shutdown(wait=True)


_STOPPING: Any = None  # in a worker: the batch's event, set once it is interrupted


class _NotStartedError(Exception):
    """A trial queued to a worker when the batch was interrupted: never started."""


def _worker_trial(spec: TrialSpec) -> dict[str, Any]:
    if _STOPPING is not None and _STOPPING.is_set():
        raise _NotStartedError(spec.index)
    return run_trial(spec)


def _worker_start(stopping: Any, parallel: bool = False) -> None:
    """A worker's start: the batch's stop event, and its signals. A terminal's Ctrl-C reaches
    every process of the job, and the batch, not each worker, decides what it means (see
    _stop_pool); SIGTERM from the batch ends the running trial as a terminated `hil run` (files
    closed, summary.json says so), and a second one the worker. With trials `parallel` on the
    cores, a trial steps its FMUs in turn (SOFTHIL_KERNEL_THREAD=0, unless the user set it): the
    kernel's worker thread pays only with a core to spare."""
    global _STOPPING
    _STOPPING = stopping
    _share_cores(parallel)
    signal.signal(signal.SIGINT, signal.SIG_IGN)

    def terminate(signum: int, frame: object) -> None:
        signal.signal(signal.SIGTERM, signal.SIG_DFL)  # once: a second one ends the worker
        raise Terminated

    signal.signal(signal.SIGTERM, terminate)


def _share_cores(parallel: bool) -> None:
    """In a worker whose trials run beside others: FMUs in turn, unless the user said."""
    if parallel:
        os.environ.setdefault(KERNEL_THREAD, "0")


def _stop_pool(pool: ProcessPoolExecutor, futures: Iterable[Future[Any]]) -> None:
    """After the batch's interrupt: drop the trials not started and wait for the running ones
    to finish. A second interrupt (Ctrl-C) while they run stops them: each worker gets
    SIGTERM, and its trial ends as a terminated run, keeping what it recorded; a third kills
    the workers. The wait is on the trials, not on the pool's shutdown: an interrupted
    Thread.join takes the pool's manager thread for stopped (CPython 3.11), and a later
    shutdown would return at once with the trials still running."""
    processes = list((getattr(pool, "_processes", None) or {}).values())
    for future in futures:  # the trials not started; cancelled here, since wait() never
        future.cancel()  # counts one that shutdown(cancel_futures=True) cancels as done
    running = [future for future in futures if not future.done()]
    pool.shutdown(wait=False)
    for signum in (None, signal.SIGTERM, signal.SIGKILL):
        if signum is not None:
            if signum == signal.SIGTERM:
                note("stopping the running trials (their folders keep what they recorded)")
            for process in processes:
                with contextlib.suppress(ProcessLookupError, ValueError, AttributeError):
                    if process.pid is not None and process.exitcode is None:
                        os.kill(process.pid, signum)
        try:
            wait(running)
            return
        except BaseException:  # noqa: BLE001 - the next interrupt; the first is re-raised
            if signum == signal.SIGKILL:
                return


def connect(address: str) -> Any:
    """A dask.distributed Client of the scheduler at `address`; one-line HilError if none."""
    try:
        from distributed import Client
    except ImportError:  # pragma: no cover - a dependency of softhil
        raise HilError(
            "--scheduler: needs dask.distributed (pip install 'dask[distributed]')"
        ) from None
    _check_address(address)
    _check_listening(address)
    try:
        # the connect timeout is dask's (distributed.comm.timeouts.connect, 30 s by default)
        client = Client(address, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as exc:
        raise HilError(f"--scheduler {address}: cannot connect: {_one_line(exc)}") from None
    return client


def _check_address(address: str) -> None:
    """Refuse an address dask cannot parse before a Client is made: a Client whose address
    fails to parse is half made, and its finaliser then waits 60 s for a loop that never ran
    (and prints a traceback) before the process can exit."""
    from distributed.comm import parse_address
    from distributed.comm.addressing import parse_host_port

    try:
        scheme, location = parse_address(address)
        if scheme in ("tcp", "tls"):
            parse_host_port(location)
    except (ValueError, TypeError) as exc:
        raise HilError(
            f"--scheduler {address}: not a scheduler address ({_one_line(exc)}); "
            "give one as tcp://HOST:PORT"
        ) from None


def _check_listening(address: str) -> None:
    """A tcp:// scheduler whose host refuses the connection is one line at once: dask retries a
    refused connection until its connect timeout (30 s) runs out."""
    import socket

    from distributed.comm import parse_address
    from distributed.comm.addressing import parse_host_port

    scheme, location = parse_address(address)
    if scheme != "tcp":
        return
    host, port = parse_host_port(location)
    try:
        socket.create_connection((host, port), timeout=5.0).close()
    except ConnectionRefusedError:
        raise HilError(
            f"--scheduler {address}: nothing listens on {host}:{port} (is the dask scheduler "
            "running there?)"
        ) from None
    except OSError:
        return  # unreachable, slow, or a name dask resolves otherwise: dask's timeout says so


def _run_dask(
    specs: Sequence[TrialSpec],
    client: Any,
    done: Callable[[TrialSpec, dict[str, Any]], None],
) -> None:
    from distributed import as_completed as dask_completed

    futures = client.map(run_trial, list(specs), pure=False)
    try:
        by_future = dict(zip(futures, specs, strict=True))
        for future in dask_completed(futures, loop=client.loop):
            spec = by_future[future]
            try:
                outcome = future.result()
            except Exception as exc:  # KilledWorker and the like: this trial is lost
                outcome = _lost(spec, exc)
            done(spec, outcome)
    except BaseException:
        client.cancel(futures)  # an interrupt: leave the cluster free for the next batch
        raise


# ------------------------------------------------------------------ the report


def aggregate(values: Sequence[float]) -> dict[str, float | int | None]:
    """mean, sample standard deviation (None below two values), min, max and n."""
    return {
        "mean": statistics.fmean(values),
        "std": statistics.stdev(values) if len(values) > 1 else None,
        "min": min(values),
        "max": max(values),
        "n": len(values),
    }


def _aggregates(outcomes: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    completed = [o for o in outcomes if o["status"] == "completed"]
    names = sorted({name for o in completed for name in o["metrics"]})
    result: dict[str, Any] = {
        "aggregate": {
            name: aggregate([o["metrics"][name] for o in completed if name in o["metrics"]])
            for name in names
        },
        "completed": len(completed),
        "failed": len(outcomes) - len(completed),
        "warned": sum(bool(o.get("warnings")) for o in completed),
    }
    if any(o["success"] is not None for o in completed):
        # a trial that failed to run did not succeed at its task either
        result["success_rate"] = sum(o["success"] is True for o in outcomes) / len(outcomes)
    return result


def report(plan: Plan, outcomes: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """The content of batch.json: deterministic, no wall-clock values."""
    trials = []
    for spec, outcome in zip(plan.trials, outcomes, strict=True):
        entry: dict[str, Any] = {
            "index": spec.index,
            "seed": spec.seed,
            "overrides": dict(spec.overrides),
            "folder": spec.name,
            "status": outcome["status"],
            "metrics": outcome["metrics"],
        }
        if outcome["error"] is not None:
            entry["error"] = outcome["error"]
        if outcome["success"] is not None:
            entry["success"] = outcome["success"]
        if outcome.get("warnings"):
            entry["warnings"] = list(outcome["warnings"])
        trials.append(entry)
    content: dict[str, Any] = {
        "command": plan.command,
        "kind": plan.kind,
        "scenario": plan.scenario,
        "scenario_sha256": plan.source_sha256,
        "seeds": list(plan.seeds),
        "trials": trials,
        **_aggregates(outcomes),
        "failed_trials": [
            {"index": t["index"], "seed": t["seed"], "folder": t["folder"], "error": t["error"]}
            for t in trials
            if t["status"] != "completed"
        ],
        "warned_trials": [
            {
                "index": t["index"],
                "seed": t["seed"],
                "folder": t["folder"],
                "warnings": t["warnings"],
            }
            for t in trials
            if "warnings" in t
        ],
    }
    if plan.kind == "sweep":
        pairs = list(zip(plan.trials, outcomes, strict=True))
        content["grid"] = {
            "keys": [o.key for o in plan.overrides],
            "values": {o.key: list(o.values) for o in plan.overrides},
        }
        content["points"] = [
            {
                "index": p,
                "overrides": dict(point),
                "trials": [s.index for s in plan.trials if s.point == p],
                **_aggregates([o for s, o in pairs if s.point == p]),
            }
            for p, point in enumerate(plan.points)
        ]
    return content


def batch_json(content: Mapping[str, Any]) -> str:
    return json.dumps(content, indent=2, sort_keys=True, allow_nan=False) + "\n"


def timing(
    plan: Plan, outcomes: Sequence[Mapping[str, Any]], execution: Execution, wall_time: float
) -> dict[str, Any]:
    """timing.json: what batch.json leaves out because it depends on the machine."""
    return {
        "executor": "dask" if execution.scheduler else "local",
        "scheduler": execution.scheduler,
        "workers": None if execution.scheduler else execution.workers or os.cpu_count(),
        "wall_time": wall_time,
        "trials": [
            {"index": o["index"], "wall_time": o["wall_time"], "host": o["host"], "pid": o["pid"]}
            for o in outcomes
        ],
    }


def run_plan(plan: Plan, execution: Execution, overwrite: bool = False) -> dict[str, Any]:
    """Run every trial into `plan.out` (new or empty) and write batch.json, timing.json and
    batch.png; returns the batch.json content. Failed trials do not raise: see its
    `failed_trials`.

    With `overwrite` the folder may hold an earlier batch's: as `hil run --overwrite` (the same
    `ResultsFolder`), it replaces only what softhil wrote there. The batch's manifest lists its
    files and its trial folders, so a foreign folder named like a trial is refused before
    anything runs; in a trial folder each trial's run replaces only its own earlier files."""
    # connect first: an unreachable scheduler leaves no results folder behind
    client = connect(execution.scheduler) if execution.scheduler else None
    planned = (*OUTPUT_FILES, *(spec.name for spec in plan.trials))
    with (
        client or contextlib.nullcontext(),
        ResultsFolder(plan.out, planned, overwrite) as folder,
    ):
        for text in folder.notes:
            note(text)
        for spec in plan.trials:  # listed before the workers make them
            folder.claim(spec.name)
        started = time.perf_counter()
        finished: dict[int, dict[str, Any]] = {}
        try:
            outcomes = execute(plan.trials, execution, client, finished)
        except (KeyboardInterrupt, Terminated) as exc:
            _write_stopped(folder, plan, finished, exc)
            raise
        wall_time = time.perf_counter() - started
        content = report(plan, outcomes)
        write_file(folder.claim("batch.json"), batch_json(content))
        text = json.dumps(timing(plan, outcomes, execution, wall_time), indent=2, sort_keys=True)
        write_file(folder.claim("timing.json"), text + "\n")
        write_file(folder.claim("batch.png"), plot(plan, content))
    return content


def _write_stopped(
    folder: ResultsFolder,
    plan: Plan,
    finished: Mapping[int, dict[str, Any]],
    exc: BaseException,
) -> None:
    """batch.json of a batch stopped by Ctrl-C or SIGTERM: the trials that finished with their
    metrics, the others failed as stopped, and `stopped` saying by what; no timing or plot. The
    finished trials' results are not lost with the rest (a full disk may refuse this too)."""
    word = "terminated" if isinstance(exc, Terminated) else "interrupted"
    outcomes = [
        finished.get(spec.index)
        or {
            "index": spec.index,
            "seed": spec.seed,
            "status": word,
            "error": f"the batch was {word} before this trial finished",
            "metrics": {},
            "success": None,
        }
        for spec in plan.trials
    ]
    content = {**report(plan, outcomes), "stopped": word}
    if "success_rate" in content:  # of the trials that finished, not of those never run
        content["success_rate"] = sum(o["success"] is True for o in finished.values()) / len(
            finished
        )
    with contextlib.suppress(HilError):
        write_file(folder.claim("batch.json"), batch_json(content))
    note(
        f"{word}: {len(finished)} of {len(plan.trials)} trials finished; their results are in "
        f"{folder.out / 'batch.json'}"
    )


# ------------------------------------------------------------------ the plot


def plot(plan: Plan, content: Mapping[str, Any]) -> bytes:
    """PNG of every metric: per trial for a batch (mean and one standard deviation drawn), or
    against the first swept key for a sweep (one line of means per combination of the others)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    names = sorted(content["aggregate"]) or ["(no metrics)"]
    cols = 1 if len(names) == 1 else 2
    rows = math.ceil(len(names) / cols)
    fig = Figure(figsize=(6.0 * cols, 2.8 * rows), layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    trials = content["trials"]
    for ax, name in zip(axes, names, strict=False):
        ax.set_title(name, fontsize=9)
        ax.grid(True, alpha=0.3)
        if plan.kind == "sweep":
            _sweep_axis(ax, plan, content, name)
        else:
            _batch_axis(ax, content, name, trials)
    for ax in axes[len(names) :]:
        ax.set_visible(False)
    failed = content["failed"]
    fig.suptitle(
        f"{plan.kind} of {plan.scenario}: {count(len(trials), 'trial')}"
        + (f", {failed} failed" if failed else ""),
        fontsize=10,
    )
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=100, metadata={"Software": None})
    return buffer.getvalue()


def _batch_axis(ax: Any, content: Mapping[str, Any], name: str, trials: Sequence[Any]) -> None:
    shown = [t for t in trials if name in t["metrics"]]
    ax.plot([t["seed"] for t in shown], [t["metrics"][name] for t in shown], "o")
    stats = content["aggregate"].get(name)
    if stats:
        ax.axhline(stats["mean"], color="C1", label="mean")
        if stats["std"] is not None:
            low, high = stats["mean"] - stats["std"], stats["mean"] + stats["std"]
            ax.axhspan(low, high, color="C1", alpha=0.15, label="+-1 std")
        ax.legend(fontsize=7)
    ax.set_xlabel("seed")


def _sweep_axis(ax: Any, plan: Plan, content: Mapping[str, Any], name: str) -> None:
    first = plan.overrides[0]
    numeric = all(isinstance(v, int | float) and not isinstance(v, bool) for v in first.values)
    position = {_canonical(v): (v if numeric else i) for i, v in enumerate(first.values)}
    series: dict[str, list[tuple[float, float]]] = {}
    dots: list[tuple[float, float]] = []
    for point in content["points"]:
        x = position[_canonical(point["overrides"][first.key])]
        rest = ", ".join(
            f"{k}={_canonical(v)}" for k, v in point["overrides"].items() if k != first.key
        )
        stats = point["aggregate"].get(name)
        if stats:
            series.setdefault(rest, []).append((x, stats["mean"]))
    for trial in content["trials"]:
        if name in trial["metrics"]:
            x = position[_canonical(trial["overrides"][first.key])]
            dots.append((x, trial["metrics"][name]))
    for label, xy in series.items():
        ax.plot(*zip(*xy, strict=True), "-", label=label or "mean")
    if dots:
        ax.plot(*zip(*dots, strict=True), ".", color="k", alpha=0.4)
    if not numeric:
        ax.set_xticks(range(len(first.values)), [str(v) for v in first.values])
    ax.set_xlabel(first.key)
    if len(series) > 1:
        ax.legend(fontsize=7)
