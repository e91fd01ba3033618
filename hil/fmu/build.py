"""The FMU build: generated sources, gcc, and a `.fmu` zip in a per-user cache.

A model folder (`fmus/NAME`) plus the glue (`fmus/common`) and headers (`fmus/include`) become
`<cache>/fmus/NAME-<digest>/NAME.fmu` and its extracted folder beside it. The digest hashes every
source file, this generator and the compiler command, so a build is reused until a source changes
and two processes building at once never see a half-written FMU (each builds in a private folder
and renames it into place). The zip is byte-reproducible (fixed timestamps, sorted entries).
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import subprocess
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

import fmus
from hil.errors import BuildError
from hil.fmu import spec as spec_module
from hil.fmu.spec import ModelSpec, generate_header, generate_model_description, guid, load_spec

CFLAGS = (
    "-std=c99",
    "-O2",
    "-fPIC",
    "-shared",
    "-fvisibility=hidden",
    "-Wall",
    "-Wextra",
    "-Werror",
)
_ZIP_DATE = (2020, 1, 1, 0, 0, 0)


@dataclass(frozen=True)
class BuiltFmu:
    """A built FMU: the zip, its extracted folder and the spec it came from."""

    name: str
    path: Path
    unzipdir: Path
    spec: ModelSpec
    guid: str


def cache_root() -> Path:
    """Per-user cache: $SOFTHIL_CACHE_DIR, else $XDG_CACHE_HOME/softhil, else ~/.cache/softhil."""
    explicit = os.environ.get("SOFTHIL_CACHE_DIR")
    if explicit:
        return Path(explicit)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "softhil"


def compiler() -> str:
    """The C compiler command: $CC or gcc."""
    return os.environ.get("CC", "gcc")


def model_folder(name: str) -> Path:
    folder = fmus.source_root() / name
    if not (folder / "model.toml").is_file():
        known = ", ".join(fmus.model_names())
        raise BuildError(f"unknown FMU model {name!r}; known models: {known}")
    return folder


def _source_files(folder: Path) -> list[Path]:
    root = fmus.source_root()
    files = [*sorted((root / "include").glob("*.h")), *sorted((root / "common").glob("*.[ch]"))]
    return files + sorted(p for p in folder.iterdir() if p.suffix in {".c", ".h", ".toml"})


def sources_digest(name: str) -> str:
    """Hash of everything that determines the FMU's bytes."""
    h = hashlib.sha256()
    h.update(" ".join((compiler(), *CFLAGS)).encode())
    for generator in (Path(spec_module.__file__), Path(__file__)):
        h.update(generator.read_bytes())
    for path in _source_files(model_folder(name)):
        h.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


def build_fmu(name: str, *, force: bool = False) -> BuiltFmu:
    """Build (or reuse from the cache) the FMU of model `name`."""
    folder = model_folder(name)
    spec = load_spec(folder)
    digest = sources_digest(name)
    model_guid = guid(spec, digest)
    target = cache_root() / "fmus" / f"{name}-{digest[:16]}"
    fmu_path = target / f"{name}.fmu"
    if fmu_path.is_file() and not force:
        return BuiltFmu(name, fmu_path, target / "unzipped", spec, model_guid)
    target.parent.mkdir(parents=True, exist_ok=True)
    work = Path(tempfile.mkdtemp(prefix=f".{name}-", dir=target.parent))
    try:
        _build_into(work, folder, spec, model_guid)
        if target.exists():
            shutil.rmtree(target, ignore_errors=True)
        try:
            os.replace(work, target)
        except OSError:
            if not fmu_path.is_file():  # someone else's identical build did not win either
                raise
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return BuiltFmu(name, fmu_path, target / "unzipped", spec, model_guid)


def _build_into(work: Path, folder: Path, spec: ModelSpec, model_guid: str) -> None:
    root = fmus.source_root()
    unzipped = work / "unzipped"
    sources = unzipped / "sources"
    binaries = unzipped / "binaries" / "linux64"
    sources.mkdir(parents=True)
    binaries.mkdir(parents=True)
    for path in _source_files(folder):
        if path.suffix in {".c", ".h"}:
            shutil.copy2(path, sources / path.name)
    (sources / "model_variables.h").write_text(generate_header(spec, model_guid))
    c_files = ["fmu_glue.c", "model.c"]
    (unzipped / "modelDescription.xml").write_text(
        generate_model_description(spec, model_guid, source_files=c_files)
    )
    _compile([sources / f for f in c_files], binaries / f"{spec.name}.so", sources, root, folder)
    _pack(unzipped, work / f"{spec.name}.fmu")


def _compile(c_files: list[Path], output: Path, include: Path, root: Path, folder: Path) -> None:
    cc = compiler()
    if shutil.which(cc) is None:
        raise BuildError(
            f"C compiler {cc!r} not found: install gcc (Debian/Ubuntu: apt-get install gcc) "
            "or set CC"
        )
    command = [cc, *CFLAGS, f"-I{include}", *map(str, c_files), "-o", str(output), "-lm"]
    result = subprocess.run(command, capture_output=True, text=True)
    if result.returncode != 0:
        raise BuildError(_first_compiler_error(result.stderr, include, root, folder))


_DIAGNOSTIC = re.compile(
    r"^(?P<file>[^:\n]+):(?P<line>\d+):(?:\d+:)? (?:fatal )?error: (?P<msg>.*)$", re.MULTILINE
)


def _first_compiler_error(stderr: str, include: Path, root: Path, folder: Path) -> str:
    """One line: the original source file and line of the first compiler error."""
    match = _DIAGNOSTIC.search(stderr)
    if not match:
        tail = stderr.strip().splitlines()[-1:] or ["(no output)"]
        return f"compiling {folder.name} failed: {tail[0]}"
    name = Path(match["file"]).name
    for candidate in (folder / name, root / "common" / name, root / "include" / name):
        if candidate.is_file():
            name = str(candidate)
            break
    return f"{name}:{match['line']}: error: {match['msg']}"


def _pack(unzipped: Path, fmu_path: Path) -> None:
    with zipfile.ZipFile(fmu_path, "w", zipfile.ZIP_DEFLATED) as zf:
        for path in sorted(p for p in unzipped.rglob("*") if p.is_file()):
            info = zipfile.ZipInfo(path.relative_to(unzipped).as_posix(), date_time=_ZIP_DATE)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, path.read_bytes())
