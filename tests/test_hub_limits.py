"""Limits of the loopback CAN hub: clients, buffered bytes, log volume; one-line setup errors.

Memory is measured as the hub's own buffered-bytes counter, not the process RSS. Everything runs
on 127.0.0.1; waits are receive timeouts and events, never sleeps, and nothing asserts on time.
"""

from __future__ import annotations

import logging
import random
import re
import socket
import struct
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from hil.bus import loopback
from hil.bus.loopback import (
    MIN_CLIENT_SHARE,
    HubSettingError,
    LoopbackHub,
    limits,
    main,
    standalone,
)
from tests.helpers import blocking_sockets_time_out

ROOT = Path(__file__).resolve().parents[1]
TIMEOUT = 10.0  # upper bound for any single wait; never reached when things work
FRAME_RE = re.compile(rb"< frame ([0-9A-F]{3}|[0-9A-F]{8}) (\d+)\.(\d{6}) ([0-9A-F]*) >")


@pytest.fixture(autouse=True)
def _guard_blocking_sockets() -> Iterator[None]:
    with blocking_sockets_time_out(TIMEOUT):
        yield


class Raw:
    """A socketcand client on a plain TCP socket."""

    def __init__(self, port: int, channel: str | None = None, *, rcvbuf: int | None = None):
        self.sock = socket.socket()
        if rcvbuf is not None:  # before connect, so the window stays small
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)
        self.sock.settimeout(TIMEOUT)
        self.sock.connect(("127.0.0.1", port))
        self.buf = b""
        if channel is not None:
            self.sock.sendall(f"< open {channel} >< rawmode >".encode())

    def handshake(self) -> None:
        """Read the greeting and both replies of the handshake sent in the constructor."""
        assert [self.read_msg() for _ in range(3)] == [b"< hi >", b"< ok >", b"< ok >"]

    def read_msg(self) -> bytes:
        while b">" not in self.buf:
            chunk = self.sock.recv(1 << 20)
            assert chunk, "hub closed the connection"
            self.buf += chunk
        end = self.buf.index(b">") + 1
        msg, self.buf = self.buf[:end].strip(), self.buf[end:]
        return msg

    def read_frames(self, n: int) -> list[int]:
        """Counters (first data byte pair, big-endian) of the next ``n`` frames."""
        out = []
        for _ in range(n):
            match = FRAME_RE.fullmatch(self.read_msg())
            assert match, "not a frame"
            out.append(int(match[4][:8], 16))
        return out

    def close(self) -> None:
        self.sock.close()


def counted_batch(start: int, n: int) -> bytes:
    """``n`` send commands whose first four data bytes count up (big-endian) from ``start``."""
    return b"".join(
        b"< send 123 8 %s 0 ff ff ff >" % b" ".join(b"%x" % x for x in struct.pack(">I", i))
        for i in range(start, start + n)
    )


def test_counted_batch_is_what_the_hub_accepts() -> None:
    assert counted_batch(0x01020304, 1) == b"< send 123 8 1 2 3 4 0 ff ff ff >"


# ---------------------------------------------------------------------------- buffered bytes


def test_stalled_client_is_dropped_at_its_share_while_the_others_get_every_frame() -> None:
    with LoopbackHub(max_clients=4, max_buffer_bytes=4 * 1024 * 1024) as hub:
        share = hub.max_client_buffer
        assert share == 1024 * 1024
        stalled = Raw(hub.port, "s", rcvbuf=4096)  # handshakes, then never reads again
        sender, reader = Raw(hub.port, "s"), Raw(hub.port, "s")
        try:
            sender.handshake()
            reader.handshake()
            batch, sent = 2000, 0
            for _ in range(200):  # up to 19 MB of frames, far beyond any kernel buffer
                sender.sock.sendall(counted_batch(sent, batch))
                assert reader.read_frames(batch) == list(range(sent, sent + batch))
                sent += batch
                if hub.slow_clients_dropped:
                    break
            assert hub.slow_clients_dropped == 1, "stalled client was never disconnected"
            # The well-behaved clients stay connected and keep getting every frame, in order.
            sender.sock.sendall(counted_batch(sent, batch))
            assert reader.read_frames(batch) == list(range(sent, sent + batch))
            assert hub.clients == 2
            # Memory: the hub never held more than its total budget; the stalled client no
            # more than its share (plus the reader's in-flight frames).
            assert hub.buffered_bytes_peak <= 4 * 1024 * 1024
            assert hub.buffered_bytes_peak < 2 * share
        finally:
            sender.close()
            reader.close()
            stalled.close()
    assert hub.buffered_bytes == 0  # every disconnect returns its bytes to the budget


def test_a_client_may_hold_exactly_its_share_and_not_one_frame_more() -> None:
    """The share bounds the bytes held for a client, inclusive. Frames held during a (long)
    handshake grace never reach its socket, so the bytes counted are exactly those queued."""
    frame = (0x123, False, bytes(8))
    size = len(b"< frame 123 1700000000.000000 0000000000000000 >")
    fit = MIN_CLIENT_SHARE // size + 1
    hub = LoopbackHub(max_clients=1, max_buffer_bytes=fit * size, handshake_grace=3600.0)
    member = hub.host("s")
    client = Raw(hub.port, "s")
    try:
        for _ in range(10):  # accept, then the handshake: a turn each at most
            if hub.clients:
                break
            hub.poll(TIMEOUT)
        client.handshake()
        hub.send_from(member, [frame] * fit)
        assert (hub.buffered_bytes, hub.slow_clients_dropped) == (fit * size, 0)
        hub.send_from(member, [frame])
        assert (hub.buffered_bytes, hub.slow_clients_dropped) == (0, 1)
    finally:
        client.close()
        hub.stop()


def test_total_buffer_is_bounded_with_many_stalled_clients() -> None:
    with LoopbackHub(max_clients=8, max_buffer_bytes=8 * 64 * 1024) as hub:
        stalled = [Raw(hub.port, "m", rcvbuf=4096) for _ in range(6)]
        sender, reader = Raw(hub.port, "m"), Raw(hub.port, "m")
        try:
            sender.handshake()
            reader.handshake()
            # Batches small enough for the reader's kernel buffer: with a 64 KiB share, reading
            # only after a large batch would be stalling too.
            sent = 0
            for _ in range(2000):
                sender.sock.sendall(counted_batch(sent, 500))
                assert reader.read_frames(500) == list(range(sent, sent + 500))
                sent += 500
                if hub.slow_clients_dropped == 6:
                    break
            assert hub.slow_clients_dropped == 6
            assert hub.buffered_bytes_peak <= 8 * 64 * 1024
        finally:
            for client in [sender, reader, *stalled]:
                client.close()


# ---------------------------------------------------------------------------- client cap


def test_a_client_on_a_full_hub_is_not_taken_for_gone_and_a_newcomer_is_told_why(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """max_clients 1, held by a recorder: its hub-alive probe is refused, which meant 'the
    hub is gone' (it recorded nothing and exited 0), and a second tool's probe refusal read as
    'not a socketcand hub'; `hil bus send` to the full hub exits 1 saying so."""
    from hil.cli import main as hil_main
    from rigbus.canbus import BusOpenError, BusSpec, connection_closed, open_bus

    with LoopbackHub(max_clients=1, max_buffer_bytes=64 * 1024) as hub:
        spec = BusSpec.parse(f"loopback:127.0.0.1:{hub.port}")
        with open_bus(spec) as held:
            assert not connection_closed(held)
            with pytest.raises(BusOpenError, match=r"the hub refused the connection: too many "
                               r"clients \(max_clients 1\)$"):  # fmt: skip
                open_bus(spec)
            assert hil_main(["bus", "send", f"loopback:127.0.0.1:{hub.port}", "080#05"]) == 1
            err = capsys.readouterr().err.strip().splitlines()
            assert len(err) == 1 and "the hub refused the connection: too many clients" in err[0]
        hub.stop()
        assert connection_closed(held)


def test_an_idle_tool_on_a_full_hub_probes_it_once_a_second(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A tool on a quiet socketcand bus asks whether the hub is still there; on a full hub each
    probe is refused and logged. It asked on every empty receive (5 times a second)."""
    from hil.cli import main as hil_main

    with LoopbackHub(max_clients=1, max_buffer_bytes=64 * 1024) as hub:
        bus = f"loopback:127.0.0.1:{hub.port}"
        assert hil_main(["bus", "dump", "--bus", bus, "--timeout", "2.5"]) == 0
        assert 1 <= hub.clients_refused <= 3, hub.clients_refused
    assert capsys.readouterr().err.strip() == "0 frames, 0 decoded"


def test_a_probe_returns_only_once_the_hub_has_closed_its_side() -> None:
    """A hub slow to read the probe's close (as one is under load) still holds the place when
    a probe that only closed returns; the probe half-closes and waits for the hub's close."""
    from rigbus.canbus import BusSpec, _probe_hub

    listener = socket.create_server(("127.0.0.1", 0))
    hub_closed = threading.Event()

    def slow_hub() -> None:
        conn, _ = listener.accept()
        conn.sendall(b"< hi >")
        assert conn.recv(100) == b""  # the probe's close
        threading.Event().wait(0.3)  # a hub busy elsewhere
        hub_closed.set()
        conn.close()

    server = threading.Thread(target=slow_hub, daemon=True)
    server.start()
    try:
        _probe_hub(BusSpec.parse(f"loopback:127.0.0.1:{listener.getsockname()[1]}"), 2.0)
        assert hub_closed.is_set()
    finally:
        server.join(5)
        listener.close()


def test_a_probe_frees_its_place_before_it_returns() -> None:
    """open_bus probes a loopback hub before python-can connects: the probe held the hub's one
    place until the hub happened to read its close, so `hil bus record` on a `--max-clients 1`
    hub was refused at random (seen on CI). Once the probe returns, its place is free, and
    the hub-alive probe of connection_closed leaves it free as well."""
    from rigbus.canbus import BusSpec, _probe_hub, connection_closed

    with LoopbackHub(max_clients=1, max_buffer_bytes=64 * 1024) as hub:
        spec = BusSpec.parse(f"loopback:127.0.0.1:{hub.port}")
        for _ in range(30):
            _probe_hub(spec, 2.0)
            newcomer = Raw(hub.port)
            assert newcomer.read_msg() == b"< hi >"
            newcomer.sock.shutdown(socket.SHUT_WR)  # and leave as the probe does
            assert newcomer.sock.recv(100) == b""
            newcomer.close()
        with can.Bus(interface="socketcand", channel="c", host="127.0.0.1", port=hub.port) as bus:
            for _ in range(5):
                assert not connection_closed(bus)
        assert hub.clients_refused == 5  # only connection_closed's probes, refused while full


def test_connections_beyond_max_clients_are_refused_with_a_reason() -> None:
    with LoopbackHub(max_clients=2, max_buffer_bytes=2 * 64 * 1024) as hub:
        first, second = Raw(hub.port, "c"), Raw(hub.port)
        first.handshake()
        assert second.read_msg() == b"< hi >"
        third = Raw(hub.port)
        assert third.read_msg() == b"< error too many clients (max_clients 2) >"
        assert third.sock.recv(100) == b""
        third.close()
        with pytest.raises(can.CanError, match="too many clients"):
            can.Bus(interface="socketcand", channel="c", host="127.0.0.1", port=hub.port)
        assert hub.clients_refused == 2
        # A freed place goes to the next client. The hub sees first's close no later than
        # second's later message, so once second has its answer the place is free.
        first.close()
        second.sock.sendall(b"< rawmode >")
        assert second.read_msg() == b"< error rawmode before open >"
        with can.Bus(interface="socketcand", channel="c", host="127.0.0.1", port=hub.port):
            assert hub.clients == 1
        assert hub.clients_refused == 2
        second.close()


# ---------------------------------------------------------------------------- floods and logs


def test_junk_flood_logs_a_bounded_number_of_lines_and_others_keep_working(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.WARNING, logger="hil.bus.loopback")
    junk = random.Random(7).randbytes(11 * 1000 * 1000)  # 11 MB, seeded
    # One window for the whole test, so the count below does not depend on the machine's speed.
    with LoopbackHub(log_burst=20, log_interval=3600.0) as hub:
        kwargs = {"interface": "socketcand", "channel": "f", "host": "127.0.0.1", "port": hub.port}
        with can.Bus(**kwargs) as a, can.Bus(**kwargs) as b:
            flooder = Raw(hub.port, "f")
            flooder.handshake()
            flood = threading.Thread(target=flooder.sock.sendall, args=(junk,), daemon=True)
            flood.start()
            for i in range(2000):  # while the flood is being processed
                a.send(can.Message(arbitration_id=0x100, data=struct.pack("<I", i)))
                got = b.recv(TIMEOUT)
                assert got is not None and struct.unpack("<I", got.data)[0] == i
            flood.join(TIMEOUT)
            assert not flood.is_alive()
            # '>' closes whatever the junk left open; the frame after it proves the hub has
            # read the whole flood.
            flooder.sock.sendall(b">< send 7AA 1 aa >")
            while True:
                got = b.recv(TIMEOUT)
                assert got is not None
                if got.arbitration_id == 0x7AA:
                    break
            assert hub.clients == 3
            flooder.close()
        malformed = hub.malformed_messages
    assert malformed > 10_000  # the flood really was parsed as junk
    lines = [r.getMessage() for r in caplog.records if r.name == "hil.bus.loopback"]
    assert len(lines) == 21, lines[-3:]
    assert lines[-1] == (
        f"loopback CAN hub: suppressed {malformed - 20} similar malformed input messages "
        "(at most 20 per 3600 s are logged)"
    )
    assert hub.warnings_suppressed == malformed - 20
    assert sum(len(line) for line in lines) < 20_000  # was 15.9 MB for this flood


class _Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_rate_limited_log_per_kind_with_one_summary_line(
    caplog: pytest.LogCaptureFixture,
) -> None:
    logger = logging.getLogger("test_hub_limits.rate")
    caplog.set_level(logging.WARNING, logger=logger.name)
    clock = _Clock()
    limited = limits.RateLimitedLog(logger, burst=3, interval=10.0, clock=clock)
    for i in range(5):
        limited.log(logging.WARNING, "junk", "junk %d", i)
    limited.log(logging.ERROR, "slow", "slow client")
    assert [r.getMessage() for r in caplog.records] == ["junk 0", "junk 1", "junk 2", "slow client"]
    assert limited.suppressed == 2
    assert limited.next_deadline() == 110.0
    clock.now = 109.9
    limited.flush()
    assert len(caplog.records) == 4
    clock.now = 110.0
    limited.flush()
    assert caplog.records[-1].getMessage() == (
        "loopback CAN hub: suppressed 2 similar junk messages (at most 3 per 10 s are logged)"
    )
    assert limited.next_deadline() is None
    limited.log(logging.WARNING, "junk", "junk %d", 5)  # a new window
    assert caplog.records[-1].getMessage() == "junk 5"
    limited.flush(everything=True)  # nothing suppressed: no summary
    assert caplog.records[-1].getMessage() == "junk 5"


def test_hub_writes_the_summary_when_the_window_ends() -> None:
    seen = threading.Event()
    lines: list[str] = []

    class Catch(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            lines.append(record.getMessage())
            if "suppressed" in record.getMessage():
                seen.set()

    handler = Catch(logging.WARNING)
    hub_log = logging.getLogger("hil.bus.loopback")
    hub_log.addHandler(handler)
    try:
        with LoopbackHub(log_burst=1, log_interval=0.05) as hub:
            raw = Raw(hub.port)
            raw.sock.sendall(b"< bogus >< bogus >< bogus >")
            assert seen.wait(TIMEOUT), lines  # written by the hub's loop, not at stop()
            raw.close()
    finally:
        hub_log.removeHandler(handler)
    assert hub.warnings_suppressed >= 1
    assert len(lines) == 3 - hub.warnings_suppressed + 1


# ---------------------------------------------------------------------------- settings


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"port": 70000}, "port must be in 0..65535"),
        ({"port": -1}, "port must be in 0..65535"),
        ({"max_clients": 0}, "max_clients must be at least 1"),
        ({"max_buffer_bytes": 1024}, "max_buffer_bytes 1024 leaves each"),
        ({"handshake_grace": float("nan")}, "handshake_grace"),
        ({"log_burst": 0}, "log_burst"),
        ({"log_interval": 0.0}, "log_interval"),
    ],
)
def test_bad_settings_are_one_line_value_errors(kwargs: dict, message: str) -> None:
    with pytest.raises(HubSettingError, match=message) as info:
        LoopbackHub(**kwargs)
    assert isinstance(info.value, ValueError)
    assert "\n" not in str(info.value)


def test_the_smallest_share_allowed_is_min_client_share() -> None:
    hub = LoopbackHub(max_clients=2, max_buffer_bytes=2 * MIN_CLIENT_SHARE)
    assert hub.max_client_buffer == MIN_CLIENT_SHARE
    with pytest.raises(HubSettingError, match=f"less than {MIN_CLIENT_SHARE} bytes"):
        LoopbackHub(max_clients=2, max_buffer_bytes=2 * MIN_CLIENT_SHARE - 1)


def test_address_in_use_names_host_and_port(capsys: pytest.CaptureFixture[str]) -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        assert main(["--port", str(port)]) == 2
    err = capsys.readouterr().err
    assert err == (
        f"error: cannot listen on 127.0.0.1:{port}: address already in use "
        "(another hub or program listens there; choose another port)\n"
    )


def test_unresolvable_host_is_one_line(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    def no_dns(*args: object, **kwargs: object) -> object:
        raise socket.gaierror(socket.EAI_NONAME, "Name or service not known")

    monkeypatch.setattr(limits.socket, "getaddrinfo", no_dns)
    assert main(["--host", "no-such-host.invalid", "--port", "0"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: cannot resolve hub host 'no-such-host.invalid'")
    assert err.count("\n") == 1


def test_byte_sizes() -> None:
    assert loopback.parse_byte_size("1048576") == 1024 * 1024
    assert loopback.parse_byte_size("512K") == 512 * 1024
    assert loopback.parse_byte_size("64m") == 64 * 1024 * 1024
    assert loopback.parse_byte_size("1GiB") == 1024**3


def test_main_passes_the_limits_on(monkeypatch: pytest.MonkeyPatch) -> None:
    made: list[LoopbackHub] = []

    class Recording(LoopbackHub):
        def __init__(self, *args: object, **kwargs: object) -> None:
            super().__init__(*args, **kwargs)  # type: ignore[arg-type]
            made.append(self)

        def serve_forever(self) -> None:
            return

    monkeypatch.setattr(standalone, "LoopbackHub", Recording)
    assert main(["--port", "0", "--max-clients", "3", "--max-buffer", "3M"]) == 0
    assert made[0].max_client_buffer == 1024 * 1024


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["--port", "70000"], "hil: error: --port must be in 0..65535"),
        (["--port", "-1"], "hil: error: --port must be in 0..65535"),
        (["--host", "0.0.0.0"], "hil: error: refusing to bind the loopback CAN hub"),
        (["--host", "a" * 64], "hil: error: cannot resolve --host"),  # before any DNS query
        (["--max-clients", "0"], "hil: error: --max-clients must be at least 1, got 0"),
        (
            ["--max-clients", "1000", "--max-buffer", "1M"],
            "hil: error: --max-buffer 1048576 leaves each of --max-clients 1000 clients less",
        ),
    ],
)
def test_hil_bus_serve_errors_are_one_line(
    args: list[str], expected: str, capsys: pytest.CaptureFixture[str]
) -> None:
    """In hil's words: the flags, not the hub's setting names, and exit 1 as every hil error
    (the hub's own `python -m hil.bus.loopback` keeps its exit 2)."""
    from hil.cli import main as hil_main

    assert hil_main(["bus", "serve", *args]) == 1
    out, err = capsys.readouterr()
    assert out == ""
    assert err.startswith(expected)
    assert err.count("\n") == 1, err


def test_hil_bus_serve_address_in_use_is_one_line() -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        result = subprocess.run(
            [sys.executable, "-m", "hil", "bus", "serve", "--port", str(port)],
            cwd=ROOT,
            capture_output=True,
            text=True,
            timeout=60,
        )
    assert result.returncode == 1
    assert result.stderr.count("\n") == 1 and result.stderr.startswith("hil: error: ")
    assert f"127.0.0.1:{port}: address already in use" in result.stderr


def test_hil_bus_serve_max_buffer_is_checked_as_hil_parses_it(
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A bad --max-buffer is hil's usage error, not the usage of python -m hil.bus.loopback
    with its internal --exit-with-stdin."""
    from hil.cli import main as hil_main

    with pytest.raises(SystemExit) as done:
        hil_main(["bus", "serve", "--max-buffer", "1X"])
    err = capsys.readouterr().err
    assert done.value.code == 2 and "usage: hil bus serve" in err
    assert "not a byte size: '1X'" in err and "exit-with-stdin" not in err
