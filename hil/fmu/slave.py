"""One FMI 2.0 co-simulation FMU instance, driven through fmpy.

`FmuSlave` loads an FMU (a softhil model name, a built FMU, or any `.fmu` file), applies parameters
by name, initialises it and steps it. It captures the FMU's log messages so that every failure
becomes one `FmuError` line naming the instance, the FMI function and what the FMU said.
"""

from __future__ import annotations

import contextlib
import ctypes
import itertools
import shutil
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

from fmpy import extract, read_model_description
from fmpy.fmi1 import FMICallException
from fmpy.fmi2 import (
    FMU2Slave,
    fmi2CallbackAllocateMemoryTYPE,
    fmi2CallbackFreeMemoryTYPE,
    fmi2CallbackFunctions,
    fmi2CallbackLoggerTYPE,
)

from hil.errors import FmuError
from hil.fmu.build import BuiltFmu, build_fmu

_libc = ctypes.CDLL(None)
_calloc = _libc.calloc
_calloc.restype = ctypes.c_void_p
_calloc.argtypes = [ctypes.c_size_t, ctypes.c_size_t]
_free = _libc.free
_free.argtypes = [ctypes.c_void_p]

Value = float | int | bool

# fmpy's logger proxy (it formats the C varargs) keeps one logger for the whole process, and each
# addLoggerProxy call replaces it: with a logger per instance, every FMU's messages went to the
# instance made last. So one logger serves them all and hands each message to the list of the
# instance that sent it, found by the componentEnvironment given to fmi2Instantiate (FMI 2.0,
# 2.1.5: the FMU passes it back with every message).
_message_lists: dict[int, list[str]] = {}
_environment_ids = itertools.count(1)


def _log(
    environment: int | None, instance: bytes, status: int, category: bytes, message: bytes
) -> None:
    messages = _message_lists.get(environment or 0)
    if messages is not None:
        messages.append(message.decode("utf-8", "replace"))


_LOGGER = fmi2CallbackLoggerTYPE(_log)


class FmuSlave:
    """A co-simulation FMU instance with named variables.

    Parameters
    ----------
    fmu
        softhil model name ("DriveCylinder"), a `BuiltFmu`, or a path to an `.fmu` file.
    instance_name
        Name used in log messages and errors, e.g. "cylinder1".
    parameters
        Start values by variable name, applied before initialisation.
    start_time
        Simulation time of the first communication point [s].
    exit_initialization
        Leave initialisation mode at once; False keeps the instance in it, so that a master can
        set its connected inputs and read the initial outputs that follow from them (FMI 2.0
        initial unknowns) before calling `exit_initialization` (`do_step` also calls it).
    """

    def __init__(
        self,
        fmu: str | Path | BuiltFmu,
        instance_name: str,
        parameters: Mapping[str, Value] | None = None,
        start_time: float = 0.0,
        exit_initialization: bool = True,
    ) -> None:
        self.instance_name = instance_name
        self.initializing = False
        self.messages: list[str] = []
        self._extracted: Path | None = None
        unzipdir = self._locate(fmu)
        try:
            self.description = read_model_description(str(unzipdir))
        except Exception as exc:  # fmpy raises XML and its own validation errors
            self._remove_extracted()
            raise FmuError(f"{instance_name}: {fmu}: not a readable FMU: {exc}") from exc
        self.model_name = self.description.modelName
        self._variables = {v.name: v for v in self.description.modelVariables}
        self.time = start_time
        self._alive = False
        # the stepping kernel whose worker thread may step this instance (hil.cosim.kernel.Kernel):
        # closing waits for it
        self.stepped_by: Any = None
        try:
            if self.description.coSimulation is None:
                raise FmuError(f"{instance_name}: {self.model_name} is not a co-simulation FMU")
            try:
                self._fmu = FMU2Slave(
                    guid=self.description.guid,
                    unzipDirectory=str(unzipdir),
                    modelIdentifier=self.description.coSimulation.modelIdentifier,
                    instanceName=instance_name,
                )
            except Exception as exc:  # a missing or foreign binary
                raise FmuError(f"{instance_name}: cannot load {self.model_name}: {exc}") from exc
            self._callbacks = self._make_callbacks()
            self._call("fmi2Instantiate", self._fmu.instantiate, callbacks=self._callbacks)
        except BaseException:
            self._forget_messages()
            self._remove_extracted()
            raise
        self._alive = True
        try:
            self._initialise(parameters or {}, start_time)
            if exit_initialization:
                self.exit_initialization()
        except BaseException:
            self.close()
            raise

    def _initialise(self, parameters: Mapping[str, Value], start_time: float) -> None:
        self._call("fmi2SetupExperiment", self._fmu.setupExperiment, startTime=start_time)
        self._call("fmi2EnterInitializationMode", self._fmu.enterInitializationMode)
        for name, value in parameters.items():
            variable = self._variable(name)
            if variable.causality not in ("parameter", "input"):
                raise FmuError(
                    f"{self.instance_name}: {name} is an {variable.causality} of "
                    f"{self.model_name} and cannot be given a value"
                )
            self.set(name, value)
        self.initializing = True

    def exit_initialization(self) -> None:
        """Leave initialisation mode (once; later calls do nothing)."""
        if self.initializing:
            self._call("fmi2ExitInitializationMode", self._fmu.exitInitializationMode)
            self.initializing = False

    def _locate(self, fmu: str | Path | BuiltFmu) -> Path:
        if isinstance(fmu, BuiltFmu):
            return fmu.unzipdir
        path = Path(fmu)
        if path.suffix == ".fmu":
            if not path.is_file():
                raise FmuError(f"{path}: no such FMU file")
            try:
                self._extracted = Path(extract(str(path)))
            except Exception as exc:  # zipfile and OS errors from a corrupt file
                raise FmuError(f"{path}: not a readable FMU: {exc}") from exc
            return self._extracted
        return build_fmu(str(fmu)).unzipdir

    def _forget_messages(self) -> None:
        _message_lists.pop(getattr(self, "_environment", 0), None)

    def _remove_extracted(self) -> None:
        if self._extracted is not None:
            shutil.rmtree(self._extracted, ignore_errors=True)
            self._extracted = None

    def _make_callbacks(self) -> fmi2CallbackFunctions:
        self._environment = next(_environment_ids)
        _message_lists[self._environment] = self.messages
        callbacks = fmi2CallbackFunctions()
        callbacks.logger = _LOGGER
        callbacks.componentEnvironment = self._environment
        callbacks.allocateMemory = fmi2CallbackAllocateMemoryTYPE(_calloc)
        callbacks.freeMemory = fmi2CallbackFreeMemoryTYPE(_free)
        from fmpy.logging import addLoggerProxy  # formats the C varargs before our logger

        addLoggerProxy(ctypes.byref(callbacks))
        return callbacks

    def _call(self, function: str, method: Any, *args: Any, **kwargs: Any) -> Any:
        before = len(self.messages)
        try:
            return method(*args, **kwargs)
        except (FMICallException, Exception) as exc:
            said = "; ".join(self.messages[before:])
            if not said:  # the FMU said why in an earlier call (e.g. a lazy initialisation)
                said = f"{exc} (it last said: {self.messages[-1]})" if self.messages else str(exc)
            raise FmuError(
                f"{self.instance_name} ({self.model_name}): {function} failed: {said}"
            ) from exc

    def _variable(self, name: str):  # noqa: ANN202 - fmpy's ScalarVariable
        try:
            return self._variables[name]
        except KeyError:
            known = ", ".join(self._variables)
            raise FmuError(
                f"{self.instance_name}: {self.model_name} has no variable {name!r} (known: {known})"
            ) from None

    def value_reference(self, name: str) -> int:
        return int(self._variable(name).valueReference)

    def variable_type(self, name: str) -> str:
        return str(self._variable(name).type)

    def causality(self, name: str) -> str:
        return str(self._variable(name).causality)

    def names(self, causality: str) -> list[str]:
        """Variable names of a causality ("parameter", "input", "output") in declaration order."""
        return [v.name for v in self.description.modelVariables if v.causality == causality]

    def set(self, name: str, value: Value) -> None:
        variable = self._variable(name)
        vr = [variable.valueReference]
        if variable.type == "Real":
            self._call(f"fmi2SetReal({name})", self._fmu.setReal, vr, [float(value)])
        elif variable.type == "Integer":
            self._call(f"fmi2SetInteger({name})", self._fmu.setInteger, vr, [int(value)])
        elif variable.type == "Boolean":
            self._call(f"fmi2SetBoolean({name})", self._fmu.setBoolean, vr, [bool(value)])
        else:
            raise FmuError(f"{self.instance_name}: {name} has unsupported type {variable.type}")

    def get(self, name: str) -> Value:
        variable = self._variable(name)
        vr = [variable.valueReference]
        if variable.type == "Real":
            return float(self._call(f"fmi2GetReal({name})", self._fmu.getReal, vr)[0])
        if variable.type == "Integer":
            return int(self._call(f"fmi2GetInteger({name})", self._fmu.getInteger, vr)[0])
        if variable.type == "Boolean":
            return bool(self._call(f"fmi2GetBoolean({name})", self._fmu.getBoolean, vr)[0])
        raise FmuError(f"{self.instance_name}: {name} has unsupported type {variable.type}")

    def get_reals(self, vrs: Sequence[int]) -> list[float]:
        """Fast path for the master: Real values by value reference."""
        return list(self._call("fmi2GetReal", self._fmu.getReal, list(vrs)))

    def set_reals(self, vrs: Sequence[int], values: Iterable[float]) -> None:
        """Fast path for the master: set Real values by value reference."""
        self._call("fmi2SetReal", self._fmu.setReal, list(vrs), [float(v) for v in values])

    @property
    def alive(self) -> bool:
        """Instantiated and not yet closed."""
        return self._alive

    def fmi_handles(self) -> tuple[ctypes.CDLL, int]:
        """The FMU's loaded shared library and its instance pointer, for the stepping kernel
        (hil/cosim/kernel), which calls the FMI functions directly from C."""
        component = self._fmu.component
        return self._fmu.dll, int(getattr(component, "value", component) or 0)

    def do_step(self, time: float, step: float) -> None:
        """Advance from communication point `time` by `step` seconds (the master passes
        time = k * h from its integer tick, so no time is ever accumulated in floats here)."""
        self.exit_initialization()
        self._call(f"fmi2DoStep(t={time:.6f})", self._fmu.doStep, time, step)
        self.time = time + step

    def close(self) -> None:
        """Terminate (if possible) and free the instance; idempotent."""
        if not self._alive:
            return
        if self.stepped_by is not None:  # a kernel's worker thread may be stepping it: wait
            self.stepped_by.stop()
        self._alive = False
        with contextlib.suppress(Exception):  # an instance in error may refuse; free it anyway
            self._fmu.terminate()
        self._fmu.freeInstance()
        self._forget_messages()
        self._remove_extracted()

    def __enter__(self) -> FmuSlave:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
