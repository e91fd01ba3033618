"""One trial of a batch, in a worker: its run, and its outcome as batch.json takes it.

`run_trial` runs the trial's scenario in this process (in-process mode: plant and controller in
one thread, byte-identical to the process mode) into its own folder and never raises: a failing
trial comes back with its status and error, and the others go on. `metrics` keeps the summary's
deterministic numbers, never the wall clock's.
"""

from __future__ import annotations

import json
import os
import socket
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from hil.batch.planning import TrialSpec
from hil.errors import HilError
from hil.program import SOFTHIL
from hil.results import write_file
from hil.run import RunOptions, run_scenario
from hil.scenario import load_scenario

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
# pyplot (the run's plots) is not thread-safe: one trial at a time per worker process, so that a
# Dask worker started with several threads stays correct (it then runs them one after another)
_RUN_LOCK = threading.Lock()


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
                reports=spec.reports,
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
        outcome["error"] = one_line(exc)
    outcome.update(
        wall_time=time.perf_counter() - started, host=socket.gethostname(), pid=os.getpid()
    )
    return outcome


def one_line(exc: BaseException) -> str:
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


def lost(spec: TrialSpec, exc: BaseException) -> dict[str, Any]:
    """The outcome of a trial whose worker did not answer (killed, crashed in an FMU)."""
    return {
        "index": spec.index,
        "seed": spec.seed,
        "status": "failed",
        "error": f"worker lost: {one_line(exc)}",
        "metrics": {},
        "success": None,
        "wall_time": None,
        "host": None,
        "pid": None,
    }
