"""The per-SYNC budget of bench/bench_run.py: exclusive attribution by layer.

Invariant checked: the layers add up to the loop's total (telescoping clock reads), each layer
is charged only the time no inner layer took, and the wrapped methods are put back afterwards.
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from bench.bench_run import BUDGET_LAYERS, LayerBudget, budget_scenario, budget_wrappers


class FakeClock:
    """A clock that advances by a given amount on every read [s]."""

    def __init__(self, step: float = 1.0) -> None:
        self.now = 0.0
        self.step = step

    def __call__(self) -> float:
        self.now += self.step
        return self.now


class Inner:
    def work(self, clock: FakeClock) -> str:
        clock.now += 10.0  # the inner layer's own time
        return "inner"


class Outer(Inner):
    def run(self, clock: FakeClock, inner: Inner) -> str:
        clock.now += 100.0  # the outer layer's own time, before the inner call
        result = inner.work(clock)
        clock.now += 1000.0  # and after it
        return result


def test_exclusive_attribution_with_a_fake_clock() -> None:
    """Every clock read advances 1 s: the outer layer gets its 1100 s plus the reads that
    close its intervals, the inner layer its 10 s plus one read, the rest is other; the
    layers sum to the total exactly."""
    clock = FakeClock()
    budget = LayerBudget(clock)
    budget.wrap(Outer, "run", "codec")
    budget.wrap(Inner, "work", "bus")
    outer, inner = Outer(), Inner()
    budget.start()  # read 1 (t = 1)
    clock.now += 5.0  # other's own time
    assert outer.run(clock, inner) == "inner"  # reads at 7, 108, 119, 1120
    budget.stop()  # read at 1121
    assert budget.seconds["other"] == 6.0 + 1.0  # 1 -> 7, 1120 -> 1121
    assert budget.seconds["codec"] == 101.0 + 1001.0  # 7 -> 108, 119 -> 1120
    assert budget.seconds["bus"] == 11.0  # 108 -> 119
    assert budget.calls == {**dict.fromkeys(BUDGET_LAYERS, 0), "codec": 1, "bus": 1}
    assert budget.total == 1120.0 == sum(budget.seconds.values())
    # the outer call was made from other, the inner one from codec; the wrappers' own time out
    assert budget.nested == {**dict.fromkeys(BUDGET_LAYERS, 0), "other": 1, "codec": 1}
    corrected = budget.corrected(inner=1.0, outer=2.0)
    assert (corrected["other"], corrected["codec"], corrected["bus"]) == (5.0, 1099.0, 10.0)
    assert budget.corrected(inner=20.0, outer=0.0)["bus"] == 0.0  # floored
    budget.restore()
    assert "work" not in vars(Outer) and Outer.work is Inner.work  # inherited: deleted again
    assert Inner.work.__name__ == "work" and Outer.run.__name__ == "run"


def test_instance_wrap_and_calls_outside_the_window() -> None:
    """A bound method wrapped on an instance; calls before `start` and after `stop` count
    nowhere."""
    clock = FakeClock()
    budget = LayerBudget(clock)
    inner = Inner()
    budget.wrap(inner, "work", "estimator")
    inner.work(clock)  # before start
    budget.start()
    inner.work(clock)
    budget.stop()
    inner.work(clock)  # after stop
    assert budget.calls["estimator"] == 1
    assert budget.seconds["estimator"] == 11.0
    assert budget.total == sum(budget.seconds.values())
    budget.restore()
    assert "work" not in vars(inner)
    with pytest.raises(ValueError, match="not a budget layer"):
        budget.wrap(inner, "work", "kernel")


def test_a_short_run_adds_up(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Two segments for 0.1 s in-process: every layer of the loop is entered, the layers add
    up to the total, and the classes are as before afterwards."""
    from hil.plant import Plant
    from hil.run import RunOptions, run_scenario
    from hil.scenario import load_scenario
    from rigbus.protocol import Protocol

    monkeypatch.setattr("hil.plots.plot_run", lambda *args: None)  # post-run: not timed
    before = (Protocol.encode, Plant.run_driven, Plant.handle)
    scenario = budget_scenario(load_scenario(), 0.1, segments=2)
    budget = LayerBudget()
    budget_wrappers(budget)
    try:
        # a CSV log: no estimation report after the run (not timed, only slow)
        options = RunOptions(
            out=tmp_path / "run", inprocess=True, progress=False, can_log="can.csv"
        )
        summary = run_scenario(scenario, options).summary
    finally:
        budget.restore()
    assert (Protocol.encode, Plant.run_driven, Plant.handle) == before
    syncs = scenario.cycles + 1
    assert math.isclose(sum(budget.seconds.values()), budget.total, rel_tol=1e-9)
    assert budget.total >= float(summary["wall_time"]) > 0.0
    assert all(seconds >= 0.0 for seconds in budget.seconds.values())
    entered = {layer for layer, calls in budget.calls.items() if calls > 0}
    assert entered == set(BUDGET_LAYERS) - {"other"}
    assert budget.calls["estimator"] == budget.calls["control law"] == syncs - 1
    # every frame on the bus encoded once by its sender and decoded once by its receiver
    frames = len((tmp_path / "run" / "can.csv").read_text().splitlines()) - 1
    assert budget.calls["codec"] == 2 * frames
    assert budget.calls["plant node"] == frames - summary["frames"]["sent"]


def test_a_closed_loop_row_leaves_the_environment_as_it_found_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """full_run sets SOFTHIL_KERNEL, SOFTHIL_HUB and SOFTHIL_BUSY_POLL for its run only: a
    user's own setting is there again afterwards, and nothing else is left behind."""
    import os

    from bench.bench_run import full_run
    from hil.scenario import DEFAULT_SCENARIO, load_scenario

    monkeypatch.setenv("SOFTHIL_BUSY_POLL", "0.001")
    monkeypatch.delenv("SOFTHIL_HUB", raising=False)
    monkeypatch.delenv("SOFTHIL_KERNEL", raising=False)
    monkeypatch.delenv("SOFTHIL_KERNEL_THREAD", raising=False)
    seen: dict[str, str | None] = {}

    import bench.bench_run as bench_module

    real = bench_module.run_scenario

    def spy(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202 - run_scenario's own signature
        names = ("SOFTHIL_BUSY_POLL", "SOFTHIL_HUB", "SOFTHIL_KERNEL_THREAD")
        seen.update({k: os.environ.get(k) for k in names})
        return real(*args, **kwargs)

    monkeypatch.setattr(bench_module, "run_scenario", spy)
    scenario = budget_scenario(load_scenario(DEFAULT_SCENARIO), 0.05, 1)
    assert full_run(scenario, True, True, "thread", "0", "softhil", "0") > 0.0
    assert seen == {"SOFTHIL_BUSY_POLL": "0", "SOFTHIL_HUB": "thread", "SOFTHIL_KERNEL_THREAD": "0"}
    assert os.environ.get("SOFTHIL_BUSY_POLL") == "0.001"
    assert "SOFTHIL_HUB" not in os.environ and "SOFTHIL_KERNEL" not in os.environ
    assert "SOFTHIL_KERNEL_THREAD" not in os.environ
