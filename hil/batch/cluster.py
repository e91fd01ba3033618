"""A batch's trials on a Dask cluster: the scheduler's address checked, the trials mapped.

An address that cannot be one, or a scheduler host that refuses the connection, is one line at
once (dask would wait its connect timeout). Invariant: an interrupt cancels the batch's trials
on the cluster, leaving it free for the next batch.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from hil.batch.planning import TrialSpec
from hil.batch.trial import lost, one_line, run_trial
from hil.errors import HilError


def connect(address: str) -> Any:
    """A dask.distributed Client of the scheduler at `address`; one-line HilError if none."""
    try:
        from distributed import Client
    except ImportError:  # pragma: no cover - a dependency of softhil
        raise HilError(
            "--scheduler: needs dask.distributed (pip install 'dask[distributed]')"
        ) from None
    _check_address(address)
    _check_listening(address)
    try:
        # the connect timeout is dask's (distributed.comm.timeouts.connect, 30 s by default)
        client = Client(address, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as exc:
        raise HilError(f"--scheduler {address}: cannot connect: {one_line(exc)}") from None
    return client


def _check_address(address: str) -> None:
    """Refuse an address dask cannot parse before a Client is made: a Client whose address
    fails to parse is half made, and its finaliser then waits 60 s for a loop that never ran
    (and prints a traceback) before the process can exit."""
    from distributed.comm import parse_address
    from distributed.comm.addressing import parse_host_port

    try:
        scheme, location = parse_address(address)
        if scheme in ("tcp", "tls"):
            parse_host_port(location)
    except (ValueError, TypeError) as exc:
        raise HilError(
            f"--scheduler {address}: not a scheduler address ({one_line(exc)}); "
            "give one as tcp://HOST:PORT"
        ) from None


def _check_listening(address: str) -> None:
    """A tcp:// scheduler whose host refuses the connection is one line at once: dask retries a
    refused connection until its connect timeout (30 s) runs out."""
    import socket

    from distributed.comm import parse_address
    from distributed.comm.addressing import parse_host_port

    scheme, location = parse_address(address)
    if scheme != "tcp":
        return
    host, port = parse_host_port(location)
    try:
        socket.create_connection((host, port), timeout=5.0).close()
    except ConnectionRefusedError:
        raise HilError(
            f"--scheduler {address}: nothing listens on {host}:{port} (is the dask scheduler "
            "running there?)"
        ) from None
    except OSError:
        return  # unreachable, slow, or a name dask resolves otherwise: dask's timeout says so


def run_dask(
    specs: Sequence[TrialSpec],
    client: Any,
    done: Callable[[TrialSpec, dict[str, Any]], None],
) -> None:
    from distributed import as_completed as dask_completed

    futures = client.map(run_trial, list(specs), pure=False)
    try:
        by_future = dict(zip(futures, specs, strict=True))
        for future in dask_completed(futures, loop=client.loop):
            spec = by_future[future]
            try:
                outcome = future.result()
            except Exception as exc:  # KilledWorker and the like: this trial is lost
                outcome = lost(spec, exc)
            done(spec, outcome)
    except BaseException:
        client.cancel(futures)  # an interrupt: leave the cluster free for the next batch
        raise
