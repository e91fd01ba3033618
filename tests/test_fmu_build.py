"""The FMU toolchain: generation from one declaration, fmpy validation, caching, clear errors."""

from __future__ import annotations

import ctypes
import os
import re
import shutil
import zipfile
from pathlib import Path

import fmpy
import pytest
from fmpy.fmi1 import FMICallException
from fmpy.fmi2 import (
    FMU2Slave,
    fmi2CallbackAllocateMemoryTYPE,
    fmi2CallbackFreeMemoryTYPE,
    fmi2CallbackFunctions,
    fmi2CallbackLoggerTYPE,
)
from fmpy.logging import addLoggerProxy
from fmpy.validation import validate_fmu

import fmus
from hil.errors import BuildError, FmuError
from hil.fmu import build as build_module
from hil.fmu.build import build_fmu, compile_library
from hil.fmu.slave import FmuSlave
from hil.fmu.spec import load_spec

MODELS = ["DriveCylinder", "FeaSegment"]


@pytest.mark.parametrize("name", MODELS)
def test_fmu_passes_fmpy_validation(name: str) -> None:
    built = build_fmu(name)
    assert validate_fmu(str(built.path)) == []


@pytest.mark.parametrize("name", MODELS)
def test_xml_and_c_value_references_come_from_the_one_declaration(name: str) -> None:
    built = build_fmu(name)
    spec = load_spec(fmus.source_root() / name)
    description = fmpy.read_model_description(str(built.path))
    header = (built.unzipdir / "sources" / "model_variables.h").read_text()
    c_refs = {m[1]: int(m[2]) for m in re.finditer(r"VR_(\w+) = (\d+),", header)}
    xml_refs = {v.name: v.valueReference for v in description.modelVariables}
    declared = {v.name: v.value_reference for v in spec.variables}
    assert c_refs == xml_refs == declared
    assert description.guid in header
    for variable in description.modelVariables:
        declared_variable = spec.variable(variable.name)
        assert variable.causality == declared_variable.causality
        assert variable.unit == declared_variable.unit


@pytest.mark.parametrize("name", MODELS)
def test_fmu_zip_layout_and_fmpy_simulation(name: str) -> None:
    built = build_fmu(name)
    with zipfile.ZipFile(built.path) as zf:
        names = set(zf.namelist())
    assert {
        "modelDescription.xml",
        f"binaries/linux64/{name}.so",
        "sources/model.c",
        "sources/fmu_glue.c",
        "sources/model_variables.h",
    } <= names
    result = fmpy.simulate_fmu(str(built.path), stop_time=0.2)
    assert len(result) > 10


@pytest.fixture
def private_sources(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A copy of the FMU sources and an empty cache, so tests may edit and rebuild."""
    root = tmp_path / "fmus"
    shutil.copytree(fmus.source_root(), root)
    monkeypatch.setattr(fmus, "source_root", lambda: root)
    monkeypatch.setenv("SOFTHIL_CACHE_DIR", str(tmp_path / "cache"))
    return root


def test_build_is_cached_until_a_source_changes(private_sources: Path) -> None:
    first = build_fmu("FeaSegment")
    mtime = first.path.stat().st_mtime_ns
    again = build_fmu("FeaSegment")
    assert again.path == first.path and again.path.stat().st_mtime_ns == mtime
    model_c = private_sources / "FeaSegment" / "model.c"
    model_c.write_text(model_c.read_text() + "\n/* an edit */\n")
    changed = build_fmu("FeaSegment")
    assert changed.path != first.path
    assert changed.guid != first.guid


def test_build_is_reproducible(private_sources: Path) -> None:
    first = build_fmu("DriveCylinder").path.read_bytes()
    second = build_fmu("DriveCylinder", force=True).path.read_bytes()
    assert first == second


def test_compile_error_names_file_and_line(private_sources: Path) -> None:
    model_c = private_sources / "DriveCylinder" / "model.c"
    lines = model_c.read_text().splitlines()
    index = next(i for i, line in enumerate(lines) if "static double clamp" in line)
    lines.insert(index, "this is not C;")
    model_c.write_text("\n".join(lines) + "\n")
    with pytest.raises(BuildError) as info:
        build_fmu("DriveCylinder")
    message = str(info.value)
    assert message.startswith(f"{model_c}:{index + 1}: error:")
    assert "\n" not in message


def test_missing_compiler_says_what_to_install(
    private_sources: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("CC", "no-such-compiler-cc")
    with pytest.raises(BuildError, match="not found: install gcc"):
        build_fmu("DriveCylinder")


def test_unknown_model_lists_known_ones() -> None:
    with pytest.raises(BuildError, match="unknown FMU model 'Nope'.*DriveCylinder"):
        build_fmu("Nope")


def test_malformed_model_toml_names_file_and_key(private_sources: Path) -> None:
    toml = private_sources / "FeaSegment" / "model.toml"
    toml.write_text(toml.read_text().replace('unit = "kg"', 'unit = "furlong"', 1))
    with pytest.raises(BuildError, match=r"model.toml: parameters.mass.unit 'furlong'"):
        build_fmu("FeaSegment")


def test_a_spec_is_read_once_and_again_when_its_file_changes(private_sources: Path) -> None:
    """load_spec keeps what it read by file: the same object while model.toml is unchanged, a
    new reading once it changes, even at the same size (a sweep's plan asks thousands of
    times)."""
    folder = private_sources / "FeaSegment"
    first = load_spec(folder)
    assert load_spec(folder) is first
    toml = folder / "model.toml"
    text = toml.read_text()
    old = first.variable("mass").description
    assert old and old[0] != "X"
    toml.write_text(text.replace(old, "X" + old[1:], 1))  # the same size
    stat = toml.stat()
    os.utime(toml, ns=(stat.st_atime_ns, stat.st_mtime_ns + 1_000_000))
    second = load_spec(folder)
    assert second is not first and second.variable("mass").description == "X" + old[1:]
    toml.write_text(text.replace('unit = "kg"', 'unit = "furlong"', 1))
    with pytest.raises(BuildError, match=r"parameters.mass.unit 'furlong'"):
        load_spec(folder)


def test_cache_location_follows_environment(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    monkeypatch.delenv("SOFTHIL_CACHE_DIR", raising=False)
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert build_module.cache_root() == tmp_path / "softhil"


@pytest.mark.parametrize(
    ("name", "parameter", "value", "output", "expected"),
    [
        ("DriveCylinder", "x_start", 0.01, "x", 0.01),
        ("FeaSegment", "theta_start", 0.5, "theta", 0.5),
    ],
)
def test_outputs_follow_start_values_in_initialisation_mode(
    name: str, parameter: str, value: float, output: str, expected: float
) -> None:
    """FMI 2.0: initial unknowns can be read in initialisation mode (masters propagate start
    values through connections before exiting it)."""
    built = build_fmu(name)
    description = fmpy.read_model_description(str(built.path))
    refs = {v.name: v.valueReference for v in description.modelVariables}
    fmu = FMU2Slave(
        guid=description.guid,
        unzipDirectory=str(built.unzipdir),
        modelIdentifier=name,
        instanceName="init",
    )
    fmu.instantiate()
    try:
        fmu.setupExperiment(startTime=0.0)
        fmu.enterInitializationMode()
        fmu.setReal([refs[parameter]], [value])
        assert fmu.getReal([refs[output]])[0] == expected
        fmu.exitInitializationMode()
        assert fmu.getReal([refs[output]])[0] == expected
        fmu.terminate()
    finally:
        fmu.freeInstance()


class RawFmu:
    """A raw fmpy instance of a built FMU, initialised at t = 0 (no softhil wrapper). Its
    callbacks are set up as hil.fmu.slave does: fmpy's default logger is a ctypes callback for a
    C varargs function and crashes the process when the FMU logs an error, so the logger sits
    behind fmpy's varargs proxy, and memory comes from libc's calloc/free."""

    def __init__(self, name: str) -> None:
        built = build_fmu(name)
        description = fmpy.read_model_description(str(built.path))
        assert description.coSimulation is not None
        self.messages: list[str] = []
        self.fmu = FMU2Slave(
            guid=description.guid,
            unzipDirectory=str(built.unzipdir),
            modelIdentifier=description.coSimulation.modelIdentifier,
            instanceName="glue-check",
        )
        libc = ctypes.CDLL(None)
        libc.calloc.restype = ctypes.c_void_p
        libc.calloc.argtypes = [ctypes.c_size_t, ctypes.c_size_t]
        libc.free.argtypes = [ctypes.c_void_p]

        def logger(component, instance, status, category, message) -> None:
            self.messages.append(message.decode("utf-8", "replace"))

        # kept on self: the FMU calls them for as long as it lives
        self.callbacks = fmi2CallbackFunctions()
        self.callbacks.logger = fmi2CallbackLoggerTYPE(logger)
        self.callbacks.allocateMemory = fmi2CallbackAllocateMemoryTYPE(libc.calloc)
        self.callbacks.freeMemory = fmi2CallbackFreeMemoryTYPE(libc.free)
        addLoggerProxy(ctypes.byref(self.callbacks))
        self.fmu.instantiate(callbacks=self.callbacks)
        self.fmu.setupExperiment(startTime=0.0)
        self.fmu.enterInitializationMode()
        self.fmu.exitInitializationMode()

    def close(self) -> None:
        self.fmu.terminate()
        self.fmu.freeInstance()


@pytest.mark.parametrize("name", MODELS)
@pytest.mark.parametrize("wrong", [0.0, 2e-3, 0.5, 1e-3 - 1e-6, 1e-3 + 1e-6])
def test_do_step_only_at_the_fmus_own_communication_point(name: str, wrong: float) -> None:
    """The glue refuses a doStep whose currentCommunicationPoint is not where the FMU is (here
    t = 1 ms after one step): repeating, skipping or drifting by 1 us is an fmi2Error, and the
    refused call leaves the FMU where it was."""
    raw = RawFmu(name)
    try:
        raw.fmu.doStep(currentCommunicationPoint=0.0, communicationStepSize=1e-3)
        with pytest.raises(FMICallException) as info:
            raw.fmu.doStep(currentCommunicationPoint=wrong, communicationStepSize=1e-3)
        assert info.value.status == 3  # fmi2Error
        assert raw.messages == [
            f"fmi2DoStep: communication point {wrong:.12g} but the FMU is at 0.001"
        ]
        raw.fmu.doStep(currentCommunicationPoint=1e-3, communicationStepSize=1e-3)
        raw.fmu.doStep(currentCommunicationPoint=2e-3, communicationStepSize=1e-3)
    finally:
        raw.close()


def test_do_step_error_names_both_communication_points() -> None:
    with FmuSlave("DriveCylinder", "cylinder1") as slave:
        slave.do_step(0.0, 1e-3)
        with pytest.raises(FmuError, match="communication point 0.5 but the FMU is at 0.001"):
            slave.do_step(0.5, 1e-3)


def test_each_instance_gets_its_own_messages_however_many_are_alive() -> None:
    """fmpy's logger proxy keeps one logger per process: an FMU's message must still reach the
    instance that sent it, not the one made last (a run's cylinder1 failed with no reason)."""
    with (
        FmuSlave(
            "DriveCylinder", "cylinder1", {"v_stiction": 1e-6}, exit_initialization=False
        ) as unstable,
        FmuSlave("DriveCylinder", "cylinder2", exit_initialization=False) as sound,
    ):
        with pytest.raises(FmuError) as info:
            unstable.get("x")
        assert str(info.value).startswith(
            "cylinder1 (DriveCylinder): fmi2GetReal(x) failed: invalid parameter substep = "
        )
        assert "beyond the stability limit" in str(info.value)
        assert sound.messages == []


def test_compiled_libraries_are_cached_by_compiler_flags_salt_and_source(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """`compile_library` (the kernel, the C codec, the benchmarks): built once per compiler,
    command line (flags, and what is linked after the source), salt and source; a compiler
    error is one BuildError line and leaves nothing behind."""
    monkeypatch.setenv("SOFTHIL_CACHE_DIR", str(tmp_path))
    code = "int answer(void) { return 42; }\n"
    flags = ("-O2", "-fPIC", "-shared")
    built = compile_library("t", "lib", code, flags)
    assert compile_library("t", "lib", code, flags) == built  # reused
    others = {
        compile_library("t", "lib", code, flags, salt="abi"),
        compile_library("t", "lib", code + "\n", flags),
        compile_library("t", "lib", code, (*flags, "-O1")),
        compile_library("t", "lib", code, (*flags, "-lm")),  # -lm before the source
        compile_library("t", "lib", code, flags, link=("-lm",)),  # after it
    }
    assert built not in others and len(others) == 5
    assert ctypes.CDLL(str(built)).answer() == 42
    with pytest.raises(BuildError, match=r"compiling lib\.c failed: .*error"):
        compile_library("t", "lib", "int broken(", flags)
    assert not list((tmp_path / "t").glob(".lib-*"))  # no private build left over
