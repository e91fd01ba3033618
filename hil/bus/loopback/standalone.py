"""The loopback hub as a program of its own: its command line, its signals, its child process.

``python -m hil.bus.loopback [--host H] [--port P] [--max-clients N] [--max-buffer BYTES]``
(`main`) and ``hil bus serve`` (`serve`) serve a hub in the foreground until SIGINT or SIGTERM;
`HubProcess` starts one as a child process that cannot outlive its parent.

Key invariant: a bad setting or an address that cannot be bound is one line (`main`: exit
status 2) before anything is served, and a stopped hub restores the signal handlers it replaced.
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import re
import selectors
import signal
import sys
import threading
from collections.abc import Callable
from types import FrameType

from hil.bus.loopback.limits import DEFAULT_MAX_BUFFER_BYTES, DEFAULT_MAX_CLIENTS, check_host
from hil.bus.loopback.server import LoopbackHub
from hil.errors import BusError, HilError

DEFAULT_PORT = 29536
"""Default TCP port of the standalone hub (``python -m hil.bus.loopback``)."""


class HubProcess:
    """A loopback hub in a child process of its own, so it never waits for its parent's GIL.

    ``python -m hil.bus.loopback --port 0 --exit-with-stdin``: the child prints its port, and
    stops when its standard input (a pipe held by this object) closes, so it cannot outlive a
    parent that is killed. It runs in a session of its own: a Ctrl-C at the terminal reaches
    the parent, which then stops the hub after its own clean-up.

    Parameters
    ----------
    host
        Loopback address to bind.
    timeout
        Seconds to wait for the child to report its port.

    Raises
    ------
    BusError
        The child did not start or did not report a port in time (its last words included).
    """

    def __init__(self, host: str = "127.0.0.1", timeout: float = 10.0) -> None:
        import subprocess

        check_host(host, allow_remote=False)
        self._process = subprocess.Popen(
            [sys.executable, "-m", "hil.bus.loopback", "--host", host, "--port", "0"]
            + ["--exit-with-stdin"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            start_new_session=True,
        )
        assert self._process.stdout is not None
        ready = selectors.DefaultSelector()
        ready.register(self._process.stdout, selectors.EVENT_READ)
        found = ready.select(timeout)
        ready.close()
        line = self._process.stdout.readline() if found else b""
        match = re.search(rb" on ([0-9.]+):(\d+) ", line)
        if match is None:
            self.stop()
            raise BusError(
                f"the loopback hub process did not start within {timeout:g} s "
                f"(it said {line.decode(errors='replace').strip()!r})"
            )
        self.address = (match[1].decode(), int(match[2]))
        self._process.stdout.close()

    @property
    def port(self) -> int:
        """The hub's TCP port."""
        return self.address[1]

    @property
    def pid(self) -> int:
        """The child's process id."""
        return self._process.pid

    def stop(self, timeout: float = 5.0) -> None:
        """Close the child's standard input (it stops), then wait; SIGKILL after ``timeout`` s.
        Idempotent."""
        import subprocess

        process = self._process
        if process.stdin is not None and not process.stdin.closed:
            with contextlib.suppress(OSError):
                process.stdin.close()
        try:
            process.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


_SIZE_SUFFIXES = {"": 1, "K": 1024, "M": 1024**2, "G": 1024**3}


def parse_byte_size(text: str) -> int:
    """Parse ``--max-buffer``: a number of bytes with an optional K, M or G (binary) suffix."""
    match = re.fullmatch(r"\s*(\d+)\s*([KMG]?)(?:i?B)?\s*", text, re.IGNORECASE)
    if not match:
        raise argparse.ArgumentTypeError(f"not a byte size: {text!r} (e.g. 1048576, 512K, 64M)")
    return int(match[1]) * _SIZE_SUFFIXES[match[2].upper()]


def main(argv: list[str] | None = None) -> int:
    """Run a standalone hub until SIGINT/SIGTERM.

    Parameters
    ----------
    argv
        Command line arguments without the program name; ``sys.argv[1:]`` if ``None``.

    Returns
    -------
    int
        Process exit status (0 on a clean shutdown).
    """
    parser = argparse.ArgumentParser(
        prog="python -m hil.bus.loopback",
        description="softhil loopback CAN hub (socketcand protocol, rawmode) over TCP.",
    )
    parser.add_argument("--host", default="127.0.0.1", help="bind address (default 127.0.0.1)")
    parser.add_argument(
        "--port", type=int, default=DEFAULT_PORT, help=f"TCP port, 0 = any (default {DEFAULT_PORT})"
    )
    parser.add_argument(
        "--allow-remote",
        action="store_true",
        help="permit binding to a non-loopback address (exposes the bus to the network)",
    )
    parser.add_argument(
        "--max-clients",
        type=int,
        default=DEFAULT_MAX_CLIENTS,
        help=f"connections served at once, more are refused (default {DEFAULT_MAX_CLIENTS})",
    )
    parser.add_argument(
        "--max-buffer",
        type=parse_byte_size,
        default=DEFAULT_MAX_BUFFER_BYTES,
        metavar="BYTES",
        help="outgoing bytes buffered for all clients together, e.g. 64M or 512K; each client "
        "may use an equal share and is disconnected when it stops reading beyond it "
        "(default 64M)",
    )
    parser.add_argument(
        "--exit-with-stdin",
        action="store_true",
        help="stop when standard input closes (how a parent process that spawned the hub "
        "takes it down with itself, even if the parent is killed)",
    )
    args = parser.parse_args(argv)
    try:
        return serve(
            args.host,
            args.port,
            allow_remote=args.allow_remote,
            max_clients=args.max_clients,
            max_buffer_bytes=args.max_buffer,
            exit_with_stdin=args.exit_with_stdin,
        )
    except HilError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


def serve(
    host: str,
    port: int,
    *,
    allow_remote: bool = False,
    max_clients: int = DEFAULT_MAX_CLIENTS,
    max_buffer_bytes: int = DEFAULT_MAX_BUFFER_BYTES,
    exit_with_stdin: bool = False,
) -> int:
    """Serve a hub in this process until SIGINT/SIGTERM (or, with `exit_with_stdin`, until
    standard input closes); 0 on a clean shutdown. A bad setting or an address that cannot be
    bound raises HilError (`HubSettingError` for a setting) before anything is served."""
    logging.basicConfig(level=logging.WARNING, format="%(levelname)s %(name)s: %(message)s")
    hub = LoopbackHub(
        host,
        port,
        allow_remote=allow_remote,
        max_clients=max_clients,
        max_buffer_bytes=max_buffer_bytes,
    )
    hub.bind()

    def on_signal(signum: int, frame: FrameType | None) -> None:
        hub.stop()

    previous: dict[int, Callable[[int, FrameType | None], object] | int | None] = {}
    for sig in (signal.SIGINT, signal.SIGTERM):
        previous[sig] = signal.signal(sig, on_signal)
    if exit_with_stdin:

        def watch_parent() -> None:
            # blocks in read() without the GIL; EOF: the parent closed the pipe or died.
            # (sys.stdin.buffer is a BufferedReader here, typed as a BinaryIO without read1)
            with contextlib.suppress(OSError, ValueError):
                while sys.stdin.buffer.read(4096):  # type: ignore[union-attr]
                    pass
            hub.stop()

        threading.Thread(target=watch_parent, name="parent-watch", daemon=True).start()
    try:
        bound_host, bound_port = hub.address
        print(
            f"softhil loopback CAN hub listening on {bound_host}:{bound_port} "
            "(socketcand and softhil binary protocols)",
            flush=True,
        )
        hub.serve_forever()
    finally:
        hub.stop()
        for signum, handler in previous.items():
            signal.signal(signum, handler)
    return 0
