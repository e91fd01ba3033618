"""Planning a batch or a sweep: its trials, every one checked before anything runs.

A batch runs one scenario with N consecutive seeds; a sweep runs every point of a grid of
`--set section.key=v1,v2,...` overrides (`parse_set`), each with N seeds. `make_plan` loads the
scenario with each value of each option, then with each grid point, so that a bad value is one
line naming its option before any trial runs. Every trial is a plain picklable `TrialSpec`
carrying its whole scenario TOML text (`hil.batch.tomlwrite`), with its seed and overrides.
"""

from __future__ import annotations

import datetime
import hashlib
import itertools
import json
import math
import re
import tempfile
import tomllib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from hil.batch.tomlwrite import BARE_KEY, dumps_toml
from hil.errors import HilError, ScenarioError
from hil.program import SOFTHIL, check_controller
from hil.results import note
from hil.scenario import Scenario, load_scenario

# the top-level keys of a scenario; a --set key starting with anything else names a robot key
SECTIONS = frozenset(f.name for f in fields(Scenario) if f.name != "source")
MAX_TRIALS = 10_000  # in one batch or sweep: each is a folder of results and a worker's run
CHECK_NOTE_POINTS = 50  # a grid larger than this says that it is being checked
# a bare word on the command line (kf, ukf, frame) is taken as a string: the shell eats quotes
_BARE_WORD = re.compile(r"[A-Za-z_][A-Za-z0-9_-]*")


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
    reports: bool = True  # draw each trial's plots and reports (`--no-reports`: not)


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


def parse_set(option: str) -> Override:
    """`section.key=v1,v2,...` to an Override; values are TOML (numbers, booleans, quoted
    strings, arrays), a bare word is a string. A key whose first part is not a top-level key of
    the scenario names a key of its robot (`valve.open_time` is `robot.valve.open_time`)."""
    key, sep, text = option.partition("=")
    key = key.strip()
    if not sep or not key or not text.strip():
        raise HilError(f"--set {option}: expected section.key=value[,value...]")
    parts = key.split(".")
    if not all(BARE_KEY.fullmatch(p) for p in parts):
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


def canonical(value: Any) -> str:
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
    reports: bool = True,
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
                label = " ".join(f"{k}={canonical(v)}" for k, v in point)
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
                    reports=reports,
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
    shown = ", ".join(f"{k} = {canonical(v)}" for k, v in point) or "none"
    header = (
        f"# hil {kind} trial {index} of scenario {source.name}: seed {seed}, overrides: {shown}\n"
    )
    return header + dumps_toml({**apply_overrides(data, point), "seed": seed})
