"""The stepping kernel: the master's inner loop over FMU participants, run in C between SYNCs.

`build_kernel` compiles `kernel.c` with the FMU toolchain (same compiler, same cache root, keyed by
a digest of the source, the flags and this file) and `Kernel` binds the FMU instances fmpy loaded
and initialised: their FMI function pointers and component handles, their inputs (connection with
gain and offset, external value, or none) and outputs (a slot in one array of doubles that mirrors
`Algorithm.values`). `Kernel.advance(k_begin, k_end)` steps those FMUs exactly as
`Algorithm._step_once` would, tick by tick; the algorithm keeps everything else (Python
participants, observers, events).

`Kernel.start` and `Kernel.finish` do the same on a worker thread of the kernel's own (C, no
Python), so that the caller computes while the FMUs step; `sample_ticks` copy the values at the
start of chosen ticks for the participants the caller steps afterwards in Python.

Invariant: for the same start state the kernel and the Python master make the same FMI calls with
the same arguments, so every value is bit-identical (tests/test_kernel.py checks it); the worker
thread makes the same calls as `advance`, only on another thread.
"""

from __future__ import annotations

import ctypes
import weakref
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from hil.errors import FmuError, HilError
from hil.fmu.build import CFLAGS, compile_library
from hil.fmu.slave import FmuSlave

SOURCE = Path(__file__).with_name("kernel.c")
# -ffp-contract=off: gain * value + offset must be two roundings, as in Python, never one FMA
KERNEL_CFLAGS = (*CFLAGS, "-ffp-contract=off", "-pthread")
TYPES = {"Real": 0, "Integer": 1, "Boolean": 2}
SOURCE_NONE, SOURCE_EXTERNAL, SOURCE_CONNECTION = 0, 1, 2
_CALLS = (
    "fmi2SetReal",
    "fmi2DoStep",
    "fmi2GetReal",
    "fmi2SetInteger",
    "fmi2SetBoolean",
    "fmi2GetInteger",
    "fmi2GetBoolean",
)
_STATUS = ["ok", "warning", "discard", "error", "fatal", "pending"]

_P = ctypes.POINTER
_VOIDS = _P(ctypes.c_void_p)
_INTS = _P(ctypes.c_int)
_UINTS = _P(ctypes.c_uint)
_DOUBLES = _P(ctypes.c_double)


class _Plan(ctypes.Structure):
    _fields_ = [
        ("n_fmus", ctypes.c_int),
        ("component", _VOIDS),
        ("set_real", _VOIDS),
        ("get_real", _VOIDS),
        ("set_integer", _VOIDS),
        ("get_integer", _VOIDS),
        ("set_boolean", _VOIDS),
        ("get_boolean", _VOIDS),
        ("do_step", _VOIDS),
        ("decimation", _INTS),
        ("input_begin", _INTS),
        ("output_begin", _INTS),
        ("input_vr", _UINTS),
        ("input_type", _INTS),
        ("input_source", _INTS),
        ("input_slot", _INTS),
        ("input_gain", _DOUBLES),
        ("input_offset", _DOUBLES),
        ("input_external", _DOUBLES),
        ("input_last", _DOUBLES),
        ("input_has_last", _INTS),
        ("output_vr", _UINTS),
        ("output_type", _INTS),
        ("output_slot", _INTS),
        ("scratch_vr", _UINTS),
        ("scratch_real", _DOUBLES),
    ]


class _Job(ctypes.Structure):
    """`Job` of kernel.c: a job for the worker thread, written before `softhil_worker_go`."""

    _fields_ = [
        ("plan", _P(_Plan)),
        ("values", _DOUBLES),
        ("k_begin", ctypes.c_longlong),
        ("k_end", ctypes.c_longlong),
        ("h", ctypes.c_double),
        ("sample_ticks", _P(ctypes.c_longlong)),
        ("n_samples", ctypes.c_int),
        ("samples", _DOUBLES),
        ("n_values", ctypes.c_int),
    ]


class _Failure(ctypes.Structure):
    _fields_ = [
        ("tick", ctypes.c_longlong),
        ("fmu", ctypes.c_int),
        ("function", ctypes.c_int),
        ("index", ctypes.c_int),
        ("status", ctypes.c_int),
    ]


def build_kernel() -> Path:
    """The kernel's shared library, built once per source (and this file, which lays out its
    plan) into the user cache."""
    return compile_library(
        "kernel", "kernel", SOURCE, KERNEL_CFLAGS, salt=Path(__file__).read_text()
    )


_library: ctypes.CDLL | None = None


def load_kernel() -> ctypes.CDLL:
    global _library  # noqa: PLW0603 - the loaded library is immutable code, loaded once
    if _library is None:
        library = ctypes.CDLL(str(build_kernel()))
        # what a stretch of stepping takes: plan, values, k_begin, k_end, h
        stretch: list[Any] = [
            _P(_Plan),
            _DOUBLES,
            ctypes.c_longlong,
            ctypes.c_longlong,
            ctypes.c_double,
        ]
        # and what it gives back: the first tick not done, the failure
        outcome: list[Any] = [_P(ctypes.c_longlong), _P(_Failure)]
        library.softhil_advance.restype = ctypes.c_int
        library.softhil_advance.argtypes = [*stretch, *outcome]
        library.softhil_worker_new.restype = ctypes.c_void_p
        library.softhil_worker_new.argtypes = [ctypes.c_double, _P(_Job)]
        # called once a period, with ctypes objects made once (a c_void_p, byrefs) and no
        # argtypes: ctypes converts nothing (0.7 us a call, against 3 us for ten typed arguments)
        library.softhil_worker_go.restype = None
        library.softhil_worker_wait.restype = ctypes.c_int
        library.softhil_worker_free.restype = None
        library.softhil_worker_free.argtypes = [ctypes.c_void_p]
        _library = library
    return _library


# (participant name, slave, decimation, [(input, type)], [(output, type, slot)])
FmuPlan = tuple[str, FmuSlave, int, list[tuple[str, str]], list[tuple[str, str, int]]]


def _array(ctype: Any, values: Sequence[Any]) -> Any:
    """A C array of `values` (at least one element, so that empty plans stay valid pointers)."""
    return (ctype * max(1, len(values)))(*values)


class _WorkerHandle:
    """The kernel's worker thread and what its jobs write into (kept alive while it may run):
    `stop` waits for a job still running (softhil_worker_free does) and ends the thread."""

    def __init__(self, library: ctypes.CDLL, arrays: tuple[Any, ...]) -> None:
        self.library = library
        self.arrays = arrays
        self.buffers: tuple[Any, ...] = ()
        self.worker: ctypes.c_void_p | None = None

    def stop(self) -> None:
        if self.worker is not None:
            worker, self.worker = self.worker, None
            self.library.softhil_worker_free(worker)


class Kernel:
    """The FMU participants of a master, bound for stepping in C.

    Parameters
    ----------
    fmus
        (participant name, slave, decimation, inputs, outputs) per FMU in the master's order;
        inputs are (name, type) and outputs (name, type, slot) with type "Real", "Integer" or
        "Boolean" and slot the index of "participant.output" in the values array.
    connections
        participant name -> [(input, source slot, gain, offset)].
    n_values
        Length of the values array (every output of every participant).
    step
        Macro step h [s].
    """

    def __init__(
        self,
        fmus: Sequence[FmuPlan],
        connections: Mapping[str, list[tuple[str, int, float, float]]],
        n_values: int,
        step: float,
    ) -> None:
        self._library = load_kernel()
        self.step = step
        self.values = (ctypes.c_double * max(1, n_values))()
        self.slaves = [slave for _, slave, _, _, _ in fmus]
        for slave in self.slaves:
            slave.stepped_by = self  # closing one waits for the worker thread
        self.decimations = [d for _, _, d, _, _ in fmus]
        self.inputs: list[tuple[int, str]] = []  # (fmu index, input name) per input
        self.outputs: list[tuple[int, str]] = []
        self._input_index: dict[tuple[str, str], int] = {}
        handles: dict[str, list[int]] = {name: [] for name in (*_CALLS, "component")}
        input_begin, output_begin = [0], [0]
        vr, kind, source, slot, gain, offset = [], [], [], [], [], []
        out_vr, out_kind, out_slot = [], [], []
        for f, (name, slave, _, inputs, outputs) in enumerate(fmus):
            dll, component = slave.fmi_handles()
            handles["component"].append(component)
            for call in _CALLS:
                handles[call].append(ctypes.cast(getattr(dll, call), ctypes.c_void_p).value or 0)
            links = {variable: (s, g, o) for variable, s, g, o in connections.get(name, [])}
            for variable, type_name in inputs:
                self._input_index[(name, variable)] = len(self.inputs)
                self.inputs.append((f, variable))
                vr.append(slave.value_reference(variable))
                kind.append(TYPES[type_name])
                s, g, o = links.get(variable, (0, 1.0, 0.0))
                source.append(SOURCE_CONNECTION if variable in links else SOURCE_NONE)
                slot.append(s)
                gain.append(float(g))
                offset.append(float(o))
            for variable, type_name, value_slot in outputs:
                self.outputs.append((f, variable))
                out_vr.append(slave.value_reference(variable))
                out_kind.append(TYPES[type_name])
                out_slot.append(value_slot)
            input_begin.append(len(vr))
            output_begin.append(len(out_vr))
        width = max(
            [b - a for a, b in zip(input_begin, input_begin[1:], strict=False)]
            + [b - a for a, b in zip(output_begin, output_begin[1:], strict=False)]
            + [1]
        )
        n_inputs = len(vr)
        self._keep = arrays = {
            "component": _array(ctypes.c_void_p, handles["component"]),
            "set_real": _array(ctypes.c_void_p, handles["fmi2SetReal"]),
            "get_real": _array(ctypes.c_void_p, handles["fmi2GetReal"]),
            "set_integer": _array(ctypes.c_void_p, handles["fmi2SetInteger"]),
            "get_integer": _array(ctypes.c_void_p, handles["fmi2GetInteger"]),
            "set_boolean": _array(ctypes.c_void_p, handles["fmi2SetBoolean"]),
            "get_boolean": _array(ctypes.c_void_p, handles["fmi2GetBoolean"]),
            "do_step": _array(ctypes.c_void_p, handles["fmi2DoStep"]),
            "decimation": _array(ctypes.c_int, self.decimations),
            "input_begin": _array(ctypes.c_int, input_begin),
            "output_begin": _array(ctypes.c_int, output_begin),
            "input_vr": _array(ctypes.c_uint, vr),
            "input_type": _array(ctypes.c_int, kind),
            "input_source": _array(ctypes.c_int, source),
            "input_slot": _array(ctypes.c_int, slot),
            "input_gain": _array(ctypes.c_double, gain),
            "input_offset": _array(ctypes.c_double, offset),
            "input_external": _array(ctypes.c_double, [0.0] * n_inputs),
            "input_last": _array(ctypes.c_double, [0.0] * n_inputs),
            "input_has_last": _array(ctypes.c_int, [0] * n_inputs),
            "output_vr": _array(ctypes.c_uint, out_vr),
            "output_type": _array(ctypes.c_int, out_kind),
            "output_slot": _array(ctypes.c_int, out_slot),
            "scratch_vr": _array(ctypes.c_uint, [0] * width),
            "scratch_real": _array(ctypes.c_double, [0.0] * width),
        }
        self._plan = _Plan(n_fmus=len(fmus), **arrays)
        self._plan_ref = ctypes.byref(self._plan)
        self._done = ctypes.c_longlong(0)
        self._failure = _Failure()
        self._job: tuple[int, int, list[int]] | None = None  # (k_begin, k_end, message counts)
        self._said = [slave.messages for slave in self.slaves]  # what each FMU logged (grows)
        self._every_tick = all(d == 1 for d in self.decimations)
        self._sample_ticks = (ctypes.c_longlong * 1)()
        self._samples = (ctypes.c_double * 1)()
        # the worker thread (C), made on first use; stopped with the kernel at the latest, the
        # arrays a job writes kept alive until then
        self._handle = _WorkerHandle(self._library, (self._keep, self.values, self._plan))
        weakref.finalize(self, self._handle.stop)
        self._worker_job = _Job(
            plan=ctypes.pointer(self._plan),
            values=ctypes.cast(self.values, _DOUBLES),
            h=self.step,
            sample_ticks=ctypes.cast(self._sample_ticks, _P(ctypes.c_longlong)),
            samples=ctypes.cast(self._samples, _DOUBLES),
            n_values=len(self.values),
        )
        self._outcome = (ctypes.byref(self._done), ctypes.byref(self._failure))

    def set_external(self, participant: str, variable: str, value: float) -> None:
        i = self._input_index[(participant, variable)]
        self._keep["input_external"][i] = value
        self._keep["input_source"][i] = SOURCE_EXTERNAL

    def load_last_inputs(self, last: Sequence[Mapping[str, float]]) -> None:
        """Take over what each FMU was last sent (per FMU, input name -> value)."""
        has, values = self._keep["input_has_last"], self._keep["input_last"]
        for i, (f, variable) in enumerate(self.inputs):
            if variable in last[f]:
                has[i], values[i] = 1, last[f][variable]
            else:
                has[i] = 0

    def store_last_inputs(self, last: Sequence[dict[str, float]]) -> None:
        """Hand back what each FMU was last sent, for the Python path to continue from."""
        has, values = self._keep["input_has_last"], self._keep["input_last"]
        for i, (f, variable) in enumerate(self.inputs):
            if has[i]:
                last[f][variable] = values[i]

    def advance(self, k_begin: int, k_end: int) -> None:
        """Step ticks k_begin .. k_end - 1; an FMU failure raises the FmuError the Python path
        would raise (instance, FMI function, what the FMU logged)."""
        self._check_alive()
        before = list(map(len, self._said))
        if self._library.softhil_advance(
            self._plan_ref, self.values, k_begin, k_end, self.step,
            ctypes.byref(self._done), ctypes.byref(self._failure),
        ):  # fmt: skip
            raise self._error(before)
        self._stepped(k_begin, k_end)

    def _check_alive(self) -> None:
        for slave in self.slaves:
            if not slave.alive:
                raise FmuError(f"{slave.instance_name}: the FMU instance is closed")

    def _stepped(self, k_begin: int, k_end: int) -> None:
        """Each slave's time after ticks k_begin .. k_end - 1 (as FmuSlave.do_step keeps it)."""
        if self._every_tick and k_end > k_begin:  # the usual rig: one time for all
            time = (k_end - 1) * self.step + self.step
            for slave in self.slaves:
                slave.time = time
            return
        for slave, d in zip(self.slaves, self.decimations, strict=True):
            last = (k_end - 1) // d * d
            if last >= k_begin:
                slave.time = last * self.step + d * self.step

    def start(self, k_begin: int, k_end: int, sample_ticks: Sequence[int], spin: float) -> None:
        """Begin stepping ticks k_begin .. k_end - 1 on the worker thread, as `advance` would,
        copying the values at the start of each of `sample_ticks` (ascending, in the range); the
        caller touches neither the values nor the FMUs until `finish`. `spin` [s]: how long the
        caller polls in `finish` before it sleeps, and the worker for the next job (fixed when
        the worker is made): waking a sleeping thread cost 10-14 us here, a twentieth of a
        6-segment period; a batch of runs sharing cores steps in turn (`hil.batch`). The job
        goes to the worker in a structure written here (`_Job`), not as arguments, which ctypes
        would convert one by one. HilError if no thread can be started."""
        if self._job is not None:
            raise HilError("the kernel's worker is busy: finish its job first")
        self._check_alive()
        if self._handle.worker is None:
            worker = self._library.softhil_worker_new(spin, ctypes.byref(self._worker_job))
            if not worker:
                raise HilError("the kernel could not start its worker thread")
            self._handle.worker = ctypes.c_void_p(worker)
            self._handle.buffers = (self._worker_job, self._sample_ticks, self._samples)
        job = self._worker_job
        n = len(sample_ticks)
        width = len(self.values)
        if len(self._sample_ticks) < n or len(self._samples) < n * width:
            self._sample_ticks = (ctypes.c_longlong * n)()
            self._samples = (ctypes.c_double * (n * width))()
            job.sample_ticks = ctypes.cast(self._sample_ticks, _P(ctypes.c_longlong))
            job.samples = ctypes.cast(self._samples, _DOUBLES)
            self._handle.buffers = (job, self._sample_ticks, self._samples)  # alive while it runs
        for i, tick in enumerate(sample_ticks):
            self._sample_ticks[i] = tick
        job.k_begin, job.k_end, job.n_samples = k_begin, k_end, n
        self._job = (k_begin, k_end, list(map(len, self._said)))
        self._library.softhil_worker_go(self._handle.worker)

    def finish(self, samples: int) -> tuple[list[list[float]], FmuError | None]:
        """Wait for the started job: the first `samples` sampled value rows that the job reached
        (taken before its failing tick, if it failed) and the FmuError `advance` would have
        raised, or None. `ticks_done` is the first tick not completed."""
        assert self._job is not None, "finish without start"
        k_begin, k_end, before = self._job
        failed = self._library.softhil_worker_wait(self._handle.worker, *self._outcome)
        self._job = None  # only now: an interrupt before this leaves the job to `stop`
        width = len(self.values)
        # as floats in one conversion (numpy's view of the buffer), not a ctypes slice a row
        # (numpy's stubs take no ctypes array, although one exports the buffer protocol)
        view = np.frombuffer(self._samples, dtype=np.float64, count=samples * width)  # type: ignore[call-overload]
        rows: list[list[float]] = view.reshape(samples, width).tolist()
        if failed:
            return rows, self._error(before)
        self._stepped(k_begin, k_end)
        return rows, None

    def stop(self) -> None:
        """Stop the worker thread (after waiting for a job still running); `start` makes a new
        one. A process should not fork while the thread lives."""
        self._job = None
        self._handle.stop()

    @property
    def ticks_done(self) -> int:
        """The first tick not completed by the last `advance`."""
        return int(self._done.value)

    def _error(self, before: list[int]) -> FmuError:
        failure = self._failure
        slave = self.slaves[failure.fmu]
        call = _CALLS[failure.function]
        if failure.function == 1:  # as FmuSlave.do_step names it
            function = f"{call}(t={failure.tick * self.step:.6f})"
        elif failure.index >= 0:
            table = self.inputs if failure.function in (3, 4) else self.outputs
            function = f"{call}({table[failure.index][1]})"
        else:
            function = call
        status = failure.status
        label = _STATUS[status] if 0 <= status < len(_STATUS) else "illegal return code"
        said = "; ".join(slave.messages[before[failure.fmu] :]) or (
            f"{call} failed with status {status} ({label})."
        )
        return FmuError(f"{slave.instance_name} ({slave.model_name}): {function} failed: {said}")
