"""A batch's report: batch.json's content and batch.png.

`report` orders the trials by index, aggregates every metric (over the batch, and per grid
point of a sweep) and keeps no wall-clock value, so that batch.json depends only on the
scenario, the seeds and the overrides. `plot` draws every metric per trial, or against the
first swept key.
"""

from __future__ import annotations

import io
import json
import math
import statistics
from collections.abc import Mapping, Sequence
from typing import Any

from hil.batch.planning import Plan, canonical, count


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
    position = {canonical(v): (v if numeric else i) for i, v in enumerate(first.values)}
    series: dict[str, list[tuple[float, float]]] = {}
    dots: list[tuple[float, float]] = []
    for point in content["points"]:
        x = position[canonical(point["overrides"][first.key])]
        rest = ", ".join(
            f"{k}={canonical(v)}" for k, v in point["overrides"].items() if k != first.key
        )
        stats = point["aggregate"].get(name)
        if stats:
            series.setdefault(rest, []).append((x, stats["mean"]))
    for trial in content["trials"]:
        if name in trial["metrics"]:
            x = position[canonical(trial["overrides"][first.key])]
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
