"""The FMU build: generated sources, gcc, and a `.fmu` zip in a per-user cache.

A model folder (`fmus/NAME`) plus the glue (`fmus/common`) and headers (`fmus/include`) become
`<cache>/fmus/NAME-<digest>/NAME.fmu` and its extracted folder beside it. The digest hashes every
source file, this generator and the compiler command, so a build is reused until a source changes
and two processes building at once never see a half-written FMU (each builds in a private folder
and renames it into place). A build that finds a sound entry in place when it is done (another
process installed its identical build meanwhile) drops its own and keeps that one, unless
`force`: a process already loading the entry (a parallel test worker, a second `hil run`) must
not see its files vanish. The zip is byte-reproducible (fixed timestamps, sorted entries).

Each cache entry records the SHA-256 of every file it holds in `manifest.sha256` (the format of
`sha256sum`, so `cd <entry> && sha256sum -c manifest.sha256` checks it by hand). `build_fmu`
verifies the whole entry against it on every call and rebuilds a damaged entry, saying so in one
line on stderr: `hil fmu check` tests the zip while `hil run` loads `unzipped/`, so both must be
known good. The check hashes the contents, not sizes and mtimes: an entry is ~150 kB, hashing it
costs well under a millisecond (the source digest already reads every source on each call), and a
flipped bit or a copy that kept its mtime would pass a stat check.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import os
import re
import shutil
import subprocess
import sys
import tempfile
import zipfile
from dataclasses import dataclass
from pathlib import Path

import fmus
from hil.errors import BuildError
from hil.fmu import spec as spec_module
from hil.fmu.spec import ModelSpec, generate_header, generate_model_description, guid, load_spec
from rigbus import cbuild
from rigbus.cbuild import cache_folder, cache_root, compiler

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
MANIFEST = "manifest.sha256"


@dataclass(frozen=True)
class BuiltFmu:
    """A built FMU: the zip, its extracted folder and the spec it came from."""

    name: str
    path: Path
    unzipdir: Path
    spec: ModelSpec
    guid: str


# a C file compiled into a cached shared library (`rigbus.cbuild`), failing with BuildError
compile_library = functools.partial(cbuild.compile_library, error=BuildError)


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
    """Build (or reuse from the cache, once verified) the FMU of model `name`.

    A cache entry whose files do not match its manifest is rebuilt, with a note on stderr.
    """
    folder = model_folder(name)
    spec = load_spec(folder)
    digest = sources_digest(name)
    model_guid = guid(spec, digest)
    target = cache_root() / "fmus" / f"{name}-{digest[:16]}"
    fmu_path = target / f"{name}.fmu"
    built = BuiltFmu(name, fmu_path, target / "unzipped", spec, model_guid)
    if target.exists() and not force:
        damage = cache_damage(target)
        if damage is None:
            return built
        print(f"hil: note: rebuilt {name}: {damage}", file=sys.stderr)
    cache_folder(target.parent, BuildError)
    work = Path(tempfile.mkdtemp(prefix=f".{name}-", dir=target.parent))
    try:
        _build_into(work, folder, spec, model_guid)
        _write_manifest(work)
        _install(work, target, replace_sound=force)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return built


def _install(work: Path, target: Path, *, replace_sound: bool = False) -> None:
    """Rename the complete build `work` into place as `target`, replacing a damaged entry there.

    Every step is a rename, so a reader finds either a complete entry or none (and then builds
    its own); it never finds a half-written one. A replaced entry is renamed away first and
    deleted afterwards. A sound entry found at `target` (another process installed its identical
    build while this one compiled) is kept and `work` dropped, unless `replace_sound`: replacing
    it would pull its files from under that process, which may be loading them already.
    """
    if not replace_sound and target.exists() and cache_damage(target) is None:
        return  # the caller's finally removes `work`
    old = None
    if target.exists():
        old = Path(tempfile.mkdtemp(prefix=f".{target.name}-old-", dir=target.parent))
        with contextlib.suppress(FileNotFoundError):  # another process moved it away first
            os.replace(target, old)  # onto the empty folder: atomic
    try:
        os.replace(work, target)
    except OSError as exc:
        # Another process installed its identical build in between: use it if it is sound.
        damage = cache_damage(target)
        if damage is not None:
            raise BuildError(f"could not install the FMU build into {target}: {exc}") from exc
    finally:
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)


def _file_digests(entry: Path) -> dict[str, str]:
    return {
        path.relative_to(entry).as_posix(): hashlib.sha256(path.read_bytes()).hexdigest()
        for path in sorted(entry.rglob("*"))
        if path.is_file() and path.name != MANIFEST
    }


def _write_manifest(entry: Path) -> None:
    lines = [f"{digest}  {path}\n" for path, digest in _file_digests(entry).items()]
    (entry / MANIFEST).write_text("".join(lines))


def cache_damage(entry: Path) -> str | None:
    """Why the cache entry `entry` cannot be used as it is (None: every file matches its digest).

    Files that are not in the manifest are ignored; a missing or unreadable manifest is damage.
    """
    try:
        text = (entry / MANIFEST).read_text()
    except OSError:
        return f"cached {entry.name} has no readable {MANIFEST}"
    problems = []
    for line in text.splitlines():
        digest, sep, relative = line.partition("  ")
        if not sep or len(digest) != 64:
            return f"cached {entry.name}/{MANIFEST} is malformed"
        try:
            actual = hashlib.sha256((entry / relative).read_bytes()).hexdigest()
        except FileNotFoundError:
            problems.append(f"cached {relative} is missing")
            continue
        except OSError as exc:
            problems.append(f"cached {relative} could not be read ({exc.strerror})")
            continue
        if actual != digest:
            problems.append(f"cached {relative} did not match its digest")
    if not problems:
        return None
    more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
    return problems[0] + more


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
    # the glue, the physics shared between models beside it (fmus/common/*.c), and the model
    shared = sorted(p.name for p in (root / "common").glob("*.c") if p.name != "fmu_glue.c")
    c_files = ["fmu_glue.c", *shared, "model.c"]
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
