"""Running a planned batch or sweep into its folder: batch.json, timing.json, batch.png.

`run_plan` takes the results folder (as `hil run` does, `hil.results`), runs every trial on
local worker processes (`hil.batch.local`) or on a Dask cluster (`hil.batch.cluster`), and writes
the report (`hil.batch.reporting`); the wall times, which depend on the machine, go to
timing.json only. A batch stopped by Ctrl-C or SIGTERM still writes the trials that finished.
"""

from __future__ import annotations

import contextlib
import json
import os
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from hil.batch.cluster import connect, run_dask
from hil.batch.local import run_local
from hil.batch.planning import Plan, TrialSpec
from hil.batch.reporting import batch_json, plot, report
from hil.errors import HilError, Terminated
from hil.results import ResultsFolder, note, write_file

OUTPUT_FILES = ("batch.json", "timing.json", "batch.png")


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
            run_dask(specs, client, done)
        else:
            run_local(specs, execution.workers or os.cpu_count() or 1, done)
    return [by_index[spec.index] for spec in specs]


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
