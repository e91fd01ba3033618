"""Compiling one C file into a shared library in softhil's per-user cache, the same way for the
plant's stepping kernel (`hil.cosim.kernel`), the controller's DBC codec (`rigbus.ccodec`) and the
benchmarks. It lives here, not in `hil`, because the controller never imports `hil`; `hil` uses
it through `hil.fmu.build`, which raises its own BuildError.

Invariant: a library's file name carries a digest of everything it is built from (compiler,
flags, salt, source), and it appears in the cache only whole (built privately, renamed in).
"""

from __future__ import annotations

import hashlib
import importlib.machinery
import importlib.util
import logging
import os
import shutil
import subprocess
import sys
import sysconfig
import tempfile
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from types import ModuleType
from typing import Generic, TypeVar

T = TypeVar("T")


class CompileError(RuntimeError):
    """A C file could not be compiled; the message has the compiler's first line."""


def cache_root() -> Path:
    """Per-user cache: $SOFTHIL_CACHE_DIR, else $XDG_CACHE_HOME/softhil, else ~/.cache/softhil."""
    explicit = os.environ.get("SOFTHIL_CACHE_DIR")
    if explicit:
        return Path(explicit)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "softhil"


def cache_folder(folder: Path, error: type[Exception] = CompileError) -> Path:
    """`folder` in the cache, made if needed; `error` in one line naming the cache (and the
    variable that chose it) if it cannot be made or written."""
    try:
        folder.mkdir(parents=True, exist_ok=True)
        if not os.access(folder, os.W_OK | os.X_OK):
            raise PermissionError(13, "Permission denied")
    except OSError as exc:
        name = "SOFTHIL_CACHE_DIR" if os.environ.get("SOFTHIL_CACHE_DIR") else "the cache"
        raise error(
            f"{name} {cache_root()}: cannot make or write {folder} ({exc.strerror or exc}); "
            "set SOFTHIL_CACHE_DIR to a folder you can write"
        ) from None
    return folder


# a shared library of plain C11, its exports marked, every warning an error; a * b + c in two
# roundings, as Python computes it (no fused multiply-add), so its bits are the same on every host
LIBRARY_FLAGS = (
    "-std=c11",
    "-O2",
    "-fPIC",
    "-shared",
    "-fvisibility=hidden",
    "-ffp-contract=off",
    "-Wall",
    "-Wextra",
    "-Werror",
)


def c_or_python(variable: str, c_means: str, python_means: str = "") -> str:
    """The setting ${variable}: "c" (unset or empty: `c_means`, the default) or "python" (case
    and spaces aside); ValueError naming the variable for any other value."""
    value = os.environ.get(variable, "").strip().lower() or "c"
    if value not in ("c", "python"):
        raise ValueError(
            f"{variable}={os.environ[variable]!r}: must be c ({c_means}, the default) or "
            f"python{python_means}"
        )
    return value


def compiler() -> str:
    """The C compiler command: $CC or gcc."""
    return os.environ.get("CC", "gcc")


_SOURCE = "{source}"  # where the C file goes in a command line


def compile_library(
    kind: str,
    stem: str,
    source: Path | str,
    flags: Sequence[str],
    *,
    salt: str = "",
    suffix: str = ".so",
    error: type[Exception] = CompileError,
    link: Sequence[str] = (),
) -> Path:
    """A shared library compiled from one C `source` (a file, or the code itself) with
    `compiler()` and `flags`, linked with `link` (libraries and static archives, after the
    source, as the linker needs them), once per compiler, flags, link, source and `salt`
    (whatever else the library depends on, such as an archive's version):
    `<cache>/<kind>/<stem>-<digest><suffix>`, built in a private file and
    renamed into place, so concurrent builds of the same digest never see a half-written file.
    `error` (CompileError by default), with the compiler's first line, if it cannot be built."""
    code = source.read_text() if isinstance(source, Path) else source
    cc = compiler()
    # the command line, keyed as it is run: the source's place in it included (an archive
    # before the source links nothing from it)
    command = [cc, *flags, _SOURCE, *link]
    h = hashlib.sha256(" ".join(command).encode())
    h.update(salt.encode())
    h.update(code.encode())
    target = cache_root() / kind / f"{stem}-{h.hexdigest()[:16]}{suffix}"
    if target.is_file():
        return target
    if shutil.which(cc) is None:
        raise error(f"C compiler {cc!r} not found: install gcc or set CC")
    cache_folder(target.parent, error)
    with tempfile.TemporaryDirectory(prefix=f".{stem}-", dir=target.parent) as work:
        c_file = source if isinstance(source, Path) else Path(work) / f"{stem}.c"
        if not isinstance(source, Path):
            c_file.write_text(code)
        built = Path(work) / f"{stem}{suffix}"
        result = subprocess.run(
            [str(c_file) if part is _SOURCE else part for part in command] + ["-o", str(built)],
            capture_output=True,
            text=True,
        )
        if result.returncode != 0:
            first = (result.stderr.strip().splitlines() or ["(no output)"])[0]
            raise error(f"compiling {c_file.name} failed: {first}")
        os.replace(built, target)  # atomic: a concurrent build of the same digest is identical
    return target


def compile_extension(
    kind: str,
    stem: str,
    source: Path | str,
    flags: Sequence[str],
    link: Sequence[str] = (),
    salt: str = "",
) -> Path:
    """A CPython extension module compiled from one C `source` against this Python's headers
    (`compile_library` keyed also by the Python it is built for, and `salt`); CompileError if it
    cannot be (no Python.h among them, a compiler error)."""
    include = sysconfig.get_paths()["include"]
    if not (Path(include) / "Python.h").is_file():
        raise CompileError(f"no Python.h in {include} (install the Python headers)")
    suffix = (importlib.machinery.EXTENSION_SUFFIXES or [".so"])[0]
    salt = " ".join(filter(None, (sys.version, sys.platform, salt)))  # the ABI, the caller's
    return compile_library(
        kind, stem, source, (*flags, f"-I{include}"), salt=salt, suffix=suffix, link=link
    )


def import_extension(name: str, target: Path) -> ModuleType:
    """The extension module `name` loaded from the file `target` (ImportError if it does not
    load: a damaged cache entry, which the caller builds again)."""
    loader = importlib.machinery.ExtensionFileLoader(name, str(target))
    spec = importlib.util.spec_from_file_location(name, target, loader=loader)
    if spec is None:
        raise ImportError(f"{target}: not loadable")
    module = importlib.util.module_from_spec(spec)
    loader.exec_module(module)
    return module


def load_extension(name: str, build: Callable[[], Path]) -> ModuleType:
    """The extension module `name` built by `build` (into the cache, or found there) and
    imported; a cached file that does not import (cut short, overwritten) is removed and built
    again. CompileError, OSError or ImportError if it cannot be had."""
    target = build()
    try:
        return import_extension(name, target)
    except ImportError:  # a damaged cache entry: built again
        target.unlink()
        return import_extension(name, build())


class CPart(Generic[T]):
    """A part of softhil in C with a Python fallback (the codec, the UKF's algebra, the signal
    rows): loaded by `load` (which builds it into the cache if needed) once, on first use, by
    whichever thread asks first, unless its variable says "python". `get()` is the loaded
    part or None, `failure` why it is None (None: in use, or not tried yet); a build that fails
    is warned of once on `logger` with `fallback` (what runs instead)."""

    def __init__(
        self,
        variable: str,
        c_means: str,
        load: Callable[[], T],
        logger: logging.Logger,
        fallback: str,
        python_means: str = "",
    ) -> None:
        self.variable = variable
        self._c_means, self._python_means = c_means, python_means
        self._load, self._logger, self._fallback = load, logger, fallback
        self.value: T | None = None
        self.failure: str | None = None
        self._lock = threading.Lock()

    def setting(self) -> str:
        """The variable: "c" (unset or empty: the C part where it builds) or "python";
        ValueError naming it for any other value."""
        return c_or_python(self.variable, self._c_means, self._python_means)

    def why(self) -> str | None:
        """Why the part is not in use (None: it is, or it was not tried yet)."""
        return self.failure

    def get(self) -> T | None:
        """The part, loaded (built if needed) on first use; None if it cannot be (`why`)."""
        if self.value is not None or self.failure is not None:
            return self.value
        with self._lock:
            if self.value is not None or self.failure is not None:
                return self.value
            if self.setting() == "python":
                self.failure = f"{self.variable}=python"
                return None
            try:
                self.value = self._load()
            except (CompileError, OSError, ImportError) as exc:
                self.failure = str(exc)
                # unexpected where the README's install holds (gcc, Python's headers): once
                self._logger.warning("%s: %s", self._fallback, exc)
        return self.value
