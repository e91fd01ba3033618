"""Helpers shared by the tests: FMU simulation, socket timeouts, interruptible children, a
built-in scenario with some lines replaced and its run's summary."""

from __future__ import annotations

import contextlib
import re
import signal
import socket
from collections.abc import Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from hil.fmu.build import BuiltFmu
from hil.fmu.slave import FmuSlave


def simulate(
    fmu: BuiltFmu,
    duration: float,
    outputs: list[str],
    parameters: Mapping[str, float] | None = None,
    inputs: Callable[[float], Mapping[str, float]] | None = None,
    step: float = 1e-3,
) -> dict[str, np.ndarray]:
    """Step an FMU in fmpy with inputs(t) applied before each step; outputs sampled after it.

    The returned arrays start with the values after initialisation (t = 0)."""
    n = int(round(duration / step))
    record: dict[str, list[float]] = {name: [] for name in ["time", *outputs]}
    with FmuSlave(fmu, "under_test", parameters) as slave:

        def sample(t: float) -> None:
            record["time"].append(t)
            for name in outputs:
                record[name].append(float(slave.get(name)))

        sample(0.0)
        for k in range(n):
            t = k * step
            if inputs is not None:
                for name, value in inputs(t).items():
                    slave.set(name, value)
            slave.do_step(t, step)
            sample((k + 1) * step)
    return {name: np.asarray(values) for name, values in record.items()}


SOCKET_TIMEOUT = 10.0  # [s] upper bound of any single socket wait; never reached when things work


@contextlib.contextmanager
def blocking_sockets_time_out(timeout: float = SOCKET_TIMEOUT) -> Iterator[None]:
    """python-can's socketcand client has no timeout of its own: make blocking reads time out,
    so that a broken hub fails a test instead of hanging it."""
    previous = socket.getdefaulttimeout()
    socket.setdefaulttimeout(timeout)
    try:
        yield
    finally:
        socket.setdefaulttimeout(previous)


def interruptible() -> None:
    """`preexec_fn` of a child the test stops with SIGINT: SIGINT at its default in the child,
    as in a terminal. A shell without job control starts background jobs (pytest on CI, say)
    with SIGINT ignored, the child inherits that across exec, and Python then keeps the
    inherited "ignored" instead of installing its KeyboardInterrupt handler: the child would
    never see the test's Ctrl-C."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def scenario_variant(tmp_path: Path, name: str, replace: dict[str, str], extra: str = "") -> Path:
    """The built-in scenario `name` with some `key = ...` lines replaced (the first line of each
    key), and `extra` appended, written to tmp_path."""
    from hil.scenario import resolve_scenario

    text = resolve_scenario(name).read_text()
    for key, line in replace.items():
        text, found = re.subn(rf"(?m)^{re.escape(key)} = .*$", line, text, count=1)
        assert found, key
    path = tmp_path / f"{name}.toml"
    path.write_text(text + extra)
    return path


def run_summary(
    path: Path, out: Path, inprocess: bool = True, reports: bool = False
) -> dict[str, Any]:
    """The summary of a run of the scenario file `path` into `out` (the plots and reports drawn
    only with `reports`)."""
    from hil.run import RunOptions, run_scenario
    from hil.scenario import load_scenario

    options = RunOptions(out=out, inprocess=inprocess, progress=False, reports=reports)
    result = run_scenario(load_scenario(path), options)
    return result.summary
