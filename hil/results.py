"""The results folder of a run: softhil never deletes or overwrites a file it did not create.

A run takes the folder with a lock file (`.softhil.lock`, created with O_EXCL, holding the pid of
the run; a lock left by a dead process is taken over with a note) and lists every file it writes
there in a manifest (`.softhil-manifest`, one name a line, written before the file itself), so a
later `--overwrite` can tell softhil's files from the user's: it replaces only files a manifest
names, never the input scenario, and refuses a folder whose foreign files a run would replace.
A folder of blocks a manifest names (`BLOCK_FOLDERS`: the signals' blocks) is removed only when
it holds nothing but block files.
An existing non-empty folder is refused without `--overwrite`.

Every byte a run writes goes through `write_bytes` (one place to see, and for tests to fail with
ENOSPC): line logs are written as whole records (`RecordFile`: on a failed write the file is cut
back to its last complete record and closed), small files atomically (`write_file`: a temporary
file renamed into place, so a full disk leaves no empty or half-written file behind).
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path

from hil.errors import HilError

LOCK = ".softhil.lock"
MANIFEST = ".softhil-manifest"
BATCH_FILE = "batch.json"  # a batch's summary: its folder is a batch's, not a run's

# Every file a run may write in its folder, whatever its robot (a plot is one of its robot kind's
# plot specs or figures, the CAN log one of the can.* names or the one the run was given): a run
# refuses to replace such a file that its folder's manifest does not name
RESULT_FILES = (
    "summary.json",
    "signals.csv",
    "signals.units.csv",
    "signals.mf4",
    "signals.parquet",  # a folder: the signals' column blocks (hil.blocks)
    "can.log",
    "can.asc",
    "can.blf",
    "can.trc",
    "can.csv",
    "can.mf4",
    "controller.json",
    "controller.log",
    "controller.pid",
    "controller_report.json",
    "scenario.toml",
    "curvature.png",
    "pressures.png",
    "piston.png",
    "estimation.png",
    "arm.png",
    "arm.gif",
    "arm.mp4",
    "heading.png",
    "valves.png",
    "fish.png",
    "fish.gif",
    "fish.mp4",
)
# the folders of blocks a run writes (`BLOCK_FILE` names the files in them)
BLOCK_FOLDERS = ("signals.parquet",)
BLOCK_FILE = re.compile(r"\.?part-\d{6,}\.parquet(\.partial)?")
# what `hil estimate RUN` adds to a run's folder (and to its manifest)
ESTIMATE_FILES = ("estimation.json", "estimation.png")


def is_result_file(name: str) -> bool:
    """Whether `name` is one of softhil's own result files other than a default CAN log name
    (can.*), which a CAN log named by the user must not take (compared without case, as some
    file systems do)."""
    own = {n.casefold() for n in (*RESULT_FILES, *ESTIMATE_FILES) if not n.startswith("can.")}
    return name.casefold() in own


class WriteError(HilError):
    """A results file could not be written (disk full, permissions): names the file and cause."""


class ReadOnlyError(WriteError):
    """A results folder that cannot be written (a read-only file system, no permission)."""


def write_bytes(fd: int, data: bytes) -> int:
    """os.write; the one write of every results file (tests replace it to simulate ENOSPC)."""
    return os.write(fd, data)


class _PartialWriteError(OSError):
    """A write that stopped after `written` bytes of the block (a disk filling up)."""

    def __init__(self, cause: OSError, written: int) -> None:
        super().__init__(cause.errno, cause.strerror)
        self.written = written


def _write_all(path: Path, fd: int, data: bytes) -> None:
    view = memoryview(data)
    done = 0
    while view:
        try:
            written = write_bytes(fd, bytes(view))
        except OSError as exc:
            raise _PartialWriteError(exc, done) from exc
        if written <= 0:  # pragma: no cover - os.write raises rather than returning 0
            raise _PartialWriteError(OSError(errno.EIO, "short write"), done)
        view = view[written:]
        done += written


def _cause(exc: OSError) -> str:
    return exc.strerror or str(exc)


def write_file(path: Path, data: bytes | str) -> None:
    """Write a whole file atomically (temporary file, then rename); WriteError on failure, and
    nothing of the new file is left behind."""
    if isinstance(data, str):
        data = data.encode("utf-8")
    temporary = path.with_name(f".{path.name}.partial")
    try:
        fd = os.open(temporary, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        try:
            _write_all(path, fd, data)
        finally:
            os.close(fd)
        os.replace(temporary, path)
    except OSError as exc:
        with contextlib.suppress(OSError):
            temporary.unlink()
        raise WriteError(f"{path}: cannot write: {_cause(exc)}") from None


class RecordFile:
    """A text file written in whole records: `write(text)` appends complete lines or nothing.
    After a failed write the file is cut back to its last complete record and closed; every
    later call is a no-op, so cleanup code cannot fail twice."""

    def __init__(self, path: Path) -> None:
        self.path = path
        try:
            self._fd: int | None = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o644)
        except OSError as exc:
            raise WriteError(f"{path}: cannot create: {_cause(exc)}") from None
        self._good = 0
        self._pending: list[str] = []
        self.failed: str | None = None

    @property
    def closed(self) -> bool:
        return self._fd is None

    def write(self, text: str) -> int:
        """Buffer text (what python-can's and csv's writers call); `flush` writes it."""
        if self._fd is not None:
            self._pending.append(text)
        return len(text)

    def flush(self) -> None:
        """Write the buffered whole records; WriteError (once) if the disk refuses them."""
        if self._fd is None or not self._pending:
            return
        text = "".join(self._pending)
        self._pending.clear()
        cut = text.rfind("\n") + 1  # only complete lines; a partial one waits
        if cut < len(text):
            self._pending.append(text[cut:])
        data = text[:cut].encode("utf-8")
        try:
            _write_all(self.path, self._fd, data)
        except _PartialWriteError as exc:
            # keep the whole records of the block that did reach the disk
            self._good += data.rfind(b"\n", 0, exc.written) + 1
            self._fail(exc)
        except OSError as exc:
            self._fail(exc)
        self._good += len(data)

    def _fail(self, exc: OSError) -> None:
        fd, self._fd = self._fd, None
        self._pending.clear()
        self.failed = f"{self.path}: cannot write: {_cause(exc)}"
        if fd is not None:
            with contextlib.suppress(OSError):
                os.ftruncate(fd, self._good)  # back to the last complete record
            with contextlib.suppress(OSError):
                os.close(fd)
        raise WriteError(self.failed) from None

    def close(self) -> None:
        """Flush what is complete and close; never raises after a failure was reported."""
        if self._fd is None:
            return
        try:
            self.flush()
        finally:
            if self._fd is not None:
                fd, self._fd = self._fd, None
                os.close(fd)


def _foreign_in_blocks(folder: Path) -> str | None:
    """The name of an entry of a folder of blocks that is not a block file, if any."""
    if not folder.is_dir() or folder.is_symlink():
        return None
    for entry in folder.iterdir():
        if not (BLOCK_FILE.fullmatch(entry.name) and entry.is_file() and not entry.is_symlink()):
            return entry.name
    return None


def remove_blocks(folder: Path) -> bool:
    """Remove a folder of blocks a run wrote (`BLOCK_FOLDERS`): its block files, then the folder
    if nothing else is in it; whether it was removed (False: it holds other files, kept)."""
    for entry in folder.iterdir():
        if BLOCK_FILE.fullmatch(entry.name) and entry.is_file() and not entry.is_symlink():
            try:
                entry.unlink()
            except OSError as exc:
                raise HilError(f"{entry}: cannot remove: {_cause(exc)}") from None
    if any(folder.iterdir()):
        return False
    try:
        folder.rmdir()
    except OSError as exc:
        raise HilError(f"{folder}: cannot remove: {_cause(exc)}") from None
    return True


def _batch_input(path: Path) -> bool:
    """True for a trial's scenario.toml as `hil batch` and `hil sweep` write it (its header)."""
    try:
        with path.open(encoding="utf-8", errors="replace") as file:
            first = file.readline()
    except OSError:
        return False
    return first.startswith(("# hil batch trial ", "# hil sweep trial "))


class ResultsFolder:
    """A run's hold on its results folder: the lock, the manifest, and the refusals.

    `planned` are the names the run will write; `keep` are files never to be replaced (the
    input scenario when it lies in the folder)."""

    def __init__(
        self, out: Path, planned: Iterable[str], overwrite: bool = False, keep: Iterable[Path] = ()
    ) -> None:
        self.out = out
        self.planned = list(planned)
        self.overwrite = overwrite
        self.keep = {p.resolve() for p in keep}
        self.written: list[str] = []
        self._locked = False
        self.notes: list[str] = []

    def kept(self, name: str) -> bool:
        """True if `name` in the folder is a file this run must leave alone (the input)."""
        return (self.out / name).resolve() in self.keep

    def __enter__(self) -> ResultsFolder:
        out = self.out
        if str(out) == "":
            raise HilError("--out: an empty folder name; name the results folder")
        try:
            out.mkdir(parents=True, exist_ok=True)
        except FileExistsError:
            raise HilError(f"results folder {out}: exists and is not a folder") from None
        except OSError as exc:
            raise HilError(f"results folder {out}: {_cause(exc)}") from None
        self._lock()
        try:
            self._clear()
        except BaseException:
            self.release()
            raise
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()

    def _lock(self) -> None:
        lock = self.out / LOCK
        for _ in range(3):
            try:
                fd = os.open(lock, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                pid = _lock_pid(lock)
                if pid is not None and _alive(pid):
                    raise HilError(
                        f"results folder {self.out} is in use by another run (pid {pid}, "
                        f"{lock.name}); choose another --out or wait for it"
                    ) from None
                with contextlib.suppress(FileNotFoundError):
                    lock.unlink()
                self.notes.append(
                    f"took over the stale lock of a run that is gone (pid {pid}) in {self.out}"
                )
                continue
            except OSError as exc:
                if exc.errno in (errno.EROFS, errno.EACCES, errno.EPERM):
                    raise ReadOnlyError(
                        f"results folder {self.out} is read-only ({_cause(exc)})"
                    ) from None
                raise HilError(f"results folder {self.out}: cannot lock: {_cause(exc)}") from None
            try:
                _write_all(lock, fd, f"{os.getpid()}\n".encode())
            except OSError as exc:
                os.close(fd)
                with contextlib.suppress(OSError):
                    lock.unlink()
                raise WriteError(f"{lock}: cannot write: {_cause(exc)}") from None
            os.close(fd)
            self._locked = True
            return
        raise HilError(f"results folder {self.out}: cannot take its lock")  # pragma: no cover

    def release(self) -> None:
        if self._locked:
            self._locked = False
            with contextlib.suppress(OSError):
                (self.out / LOCK).unlink()

    def _clear(self) -> None:
        """Refuse a folder holding anything but softhil's own files; with overwrite, remove the
        files an earlier run listed in its manifest (never the input scenario)."""
        present = sorted(p.name for p in self.out.iterdir() if p.name not in (LOCK, MANIFEST))
        if not present:
            return
        if not self.overwrite:
            raise HilError(
                f"results folder {self.out} is not empty ({len(present)} entries, e.g. "
                f"{present[0]!r}): choose another --out, or --overwrite to replace the files an "
                "earlier run wrote there"
            )
        ours = set(self._manifest())
        if BATCH_FILE in ours and BATCH_FILE not in self.planned:
            raise HilError(
                f"results folder {self.out} holds a batch ({BATCH_FILE} and its trials): "
                "--overwrite replaces an earlier run's files, not a whole batch; choose another "
                "--out"
            )
        self._refuse_foreign(ours)
        for name in sorted(ours):
            if "/" not in name and name not in (LOCK, MANIFEST) and not self.kept(name):
                self._remove_ours(self.out / name)
        self.written = [
            n
            for n in self._manifest()
            if (self.out / n).exists() and not ((self.out / n).is_dir() and n not in self.planned)
        ]  # a folder kept for a user's files there is no longer softhil's

    def _refuse_foreign(self, ours: set[str]) -> None:
        """HilError naming a file the run would replace, or one in a folder of blocks it would
        remove, that no manifest lists (the input scenario excepted)."""
        for name in self.planned:
            if (self.out / name).exists() and name not in ours and not self.kept(name):
                raise HilError(
                    f"results folder {self.out}: {name} was not written by softhil (not in "
                    f"{MANIFEST}); --overwrite replaces only softhil's own files"
                )
        for name in ours.intersection(BLOCK_FOLDERS):
            foreign = _foreign_in_blocks(self.out / name)
            if foreign:
                raise HilError(
                    f"results folder {self.out}: {name}/{foreign} was not written by softhil; "
                    "--overwrite replaces only softhil's own files"
                )

    def _remove_ours(self, path: Path) -> None:
        """Remove an entry an earlier run's manifest lists: a file, a folder of its blocks, or
        an earlier batch's trial this one does not have (a symbolic link stays)."""
        if path.is_symlink():
            return
        if path.is_file():
            try:
                path.unlink()
            except OSError as exc:
                raise HilError(f"{path}: cannot remove: {_cause(exc)}") from None
        elif path.name in BLOCK_FOLDERS and path.is_dir():
            remove_blocks(path)  # nothing else in it (`_clear` looked)
        elif path.is_dir() and path.name not in self.planned:
            self._remove_folder(path)

    def _remove_folder(self, path: Path) -> None:
        """Remove a results folder an earlier run made here (a batch's trial): the files its
        own manifest lists, then the folder if nothing else is in it (else it stays, noted)."""
        inner = ResultsFolder(path, ())
        names = inner._manifest()
        if _batch_input(path / "scenario.toml"):  # the trial's input, written by its batch
            names.append("scenario.toml")
        for name in names:
            entry = path / name
            if name in BLOCK_FOLDERS and entry.is_dir() and not entry.is_symlink():
                remove_blocks(entry)  # what is left of it (a user's files) keeps the trial
            elif name not in (LOCK,) and entry.is_file() and not entry.is_symlink():
                try:
                    entry.unlink()
                except OSError as exc:
                    raise HilError(f"{entry}: cannot remove: {_cause(exc)}") from None
        left = sorted(p.name for p in path.iterdir() if p.name not in (MANIFEST, LOCK))
        if left:
            (path / MANIFEST).unlink(missing_ok=True)
            self.notes.append(
                f"kept {path}: an earlier batch's trial, it holds files softhil did not write "
                f"({', '.join(left[:3])}{', ...' if len(left) > 3 else ''})"
            )
            return
        for name in (MANIFEST, LOCK):
            (path / name).unlink(missing_ok=True)
        try:
            path.rmdir()
        except OSError as exc:
            raise HilError(f"{path}: cannot remove: {_cause(exc)}") from None

    def _manifest(self) -> list[str]:
        try:
            text = (self.out / MANIFEST).read_text(encoding="utf-8", errors="replace")
        except OSError:
            return []
        return [line for line in text.splitlines() if line and "/" not in line]

    def claim(self, name: str) -> Path:
        """The path of a file this run writes, listed in the manifest before it exists."""
        if name not in self.written:
            self.written.append(name)
            write_file(self.out / MANIFEST, "".join(f"{n}\n" for n in self.written))
        return self.out / name


@contextlib.contextmanager
def locked(out: Path, writes: str) -> Iterator[None]:
    """Hold an existing results folder's lock, as a run does, while a command writes into it
    after the run (`hil estimate`): refused while a run or another command holds it, and in a
    folder that cannot be written, saying what the command `writes` there."""
    folder = ResultsFolder(out, ())
    try:
        folder._lock()
    except ReadOnlyError as exc:
        raise ReadOnlyError(f"{exc}: {writes}") from None
    try:
        for text in folder.notes:
            note(text)
        yield
    finally:
        folder.release()


def manifest_names(out: Path) -> list[str]:
    """The files a softhil command listed as its own in the folder `out` (none if no manifest)."""
    return ResultsFolder(out, ())._manifest()


def list_in_manifest(out: Path, names: Iterable[str]) -> None:
    """Add files softhil writes into a run's folder after the run (`hil estimate`'s) to the
    folder's manifest, before they are written, so that a rerun with --overwrite replaces them
    with the rest."""
    path = out / MANIFEST
    try:
        listed = [n for n in path.read_text(encoding="utf-8", errors="replace").splitlines() if n]
    except FileNotFoundError:
        listed = []
    except OSError as exc:
        raise WriteError(f"{path}: cannot read: {_cause(exc)}") from None
    missing = [n for n in names if n not in listed]
    if missing:
        write_file(path, "".join(f"{n}\n" for n in (*listed, *missing)))


def _lock_pid(lock: Path) -> int | None:
    try:
        return int(lock.read_text().strip())
    except (OSError, ValueError):
        return None


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def note(text: str) -> None:
    print(f"hil: note: {text}", file=sys.stderr)
