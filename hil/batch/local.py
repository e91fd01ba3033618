"""A batch's trials on local worker processes, and how an interrupt stops them.

The workers fork from a server process that has imported softhil once (`_context`); at the
batch's first interrupt the trials not started are dropped and those running finish, at a
second they stop as terminated runs (keeping what they recorded), at a third the workers are
killed (`_stop_pool`). Invariant: every trial that finished is reported, whatever stops the
batch.
"""

from __future__ import annotations

import contextlib
import multiprocessing
import os
import signal
from collections.abc import Callable, Iterable, Sequence
from concurrent.futures import Future, ProcessPoolExecutor, as_completed, wait
from typing import Any

from hil.batch.planning import TrialSpec
from hil.batch.trial import lost, run_trial
from hil.environment import KERNEL_THREAD
from hil.errors import HilError, Terminated
from hil.results import note


def _context() -> multiprocessing.context.BaseContext:
    """Workers forked from a fresh server process that has imported softhil once: quick to
    start, and safe even when this process runs threads (a Dask client, a progress bar)."""
    if "forkserver" in multiprocessing.get_all_start_methods():
        context = multiprocessing.get_context("forkserver")
        # the run's plotting and estimation report too: every worker forks warm
        context.set_forkserver_preload(["hil.batch.local", "hil.plots", "hil.estimation"])
        return context
    return multiprocessing.get_context("spawn")


def run_local(
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
                outcome = lost(spec, exc)
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
