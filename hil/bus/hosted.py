"""The plant's end of a run's bus when the plant hosts the loopback hub itself.

`hil run` across processes used to start the hub as a third process: every SYNC's frames then
crossed two sockets each way (plant -> hub -> controller -> hub -> plant) and woke three
processes sharing the machine's cores. A `HostedBus` is a `LoopbackHub` served from the plant's
own thread, with the plant as a member of the run's channel: the controller (python-can's
``softhil`` interface) and any tool (socketcand or binary, on the same port) connect to it as
to any hub, while the plant's frames go straight from its `send` to the other members' sockets
and theirs arrive in its `recv`, one hop and one wake-up each way.

The hub is served whenever the plant receives or sends (`LoopbackHub.poll`): while the plant
steps its physics, frames from the controller and tools wait in the sockets' buffers, in order.
Everything the hub guarantees holds: one order of frames for every member, no loss for a
connected client, the same limits. The hub stamps the frames it forwards with its receive time,
as before; the plant logs simulation time.

With `busy_poll` a receive turns the hub without sleeping for up to that long before it waits
in ``select`` (see `rigbus.binary.SofthilBus`): across processes the plant and the controller
each wait for the other once a SYNC, and on a virtual machine a sleeping process takes hundreds
of microseconds to wake.
"""

from __future__ import annotations

import os
import time
from collections.abc import Sequence

import can

from hil.bus.loopback import DEFAULT_HANDSHAKE_GRACE, LoopbackHub
from rigbus.binary import busy_poll_seconds, classic_data


class HostedBus(can.BusABC):
    """A python-can bus that is a loopback hub's own member of `channel` (see the module
    docstring); `port` is where the other members connect. `busy_poll`: seconds a receive
    turns the hub without sleeping (ValueError outside 0..1 s)."""

    def __init__(
        self,
        channel: str,
        host: str = "127.0.0.1",
        *,
        handshake_grace: float = DEFAULT_HANDSHAKE_GRACE,
        busy_poll: float = 0.0,
        **kwargs: object,
    ) -> None:
        self._busy_poll = busy_poll_seconds(busy_poll)
        self.hub = LoopbackHub(host, handshake_grace=handshake_grace)
        self._member = self.hub.host(channel)
        self.channel_name = channel
        self.channel_info = f"softhil hub hosted on {host}:{self.hub.port}, channel {channel}"
        self.closed = False
        super().__init__(channel=channel, **kwargs)  # type: ignore[arg-type]

    @property
    def busy_poll(self) -> float:
        """Seconds a receive polls before it sleeps (0: at once)."""
        return self._busy_poll

    @property
    def port(self) -> int:
        return self.hub.port

    def watch(self, can_id: int) -> None:
        """Remember which connection sends frames of `can_id` (see `sender_gone`)."""
        self._member.watch_id = can_id

    def elsewhere(self) -> list[str]:
        """The other channels of the hub that clients joined (a controller that named the
        wrong one is there, not on this bus)."""
        return [name for name in self.hub.joined() if name != self.channel_name]

    def sender_gone(self) -> str | None:
        """Where the last connection that sent a watched frame was connected from, if that
        connection has closed; None while it is open or before any such frame."""
        sender = self._member.watched
        return sender.addr if sender is not None and sender.closed else None

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.send_batch([msg])

    def send_batch(self, messages: Sequence[can.Message]) -> None:
        """Send frames in order, forwarded to the other members at once; nothing is sent if
        any frame is invalid (only classic data frames are carried)."""
        if self.closed:
            raise can.CanOperationError("softhil bus: the hosted hub is shut down")
        frames = [(m.arbitration_id, m.is_extended_id, classic_data(m)) for m in messages]
        self.hub.send_from(self._member, frames)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        inbox = self._member.inbox
        if not inbox:
            if self.closed:
                raise can.CanOperationError("softhil bus: the hosted hub is shut down")
            now = time.monotonic()
            deadline = None if timeout is None else now + timeout
            busy_until = now + self._busy_poll
            while True:
                if now < busy_until:
                    self.hub.poll(0.0)  # busy_poll: turn the hub without sleeping
                    os.sched_yield()  # a process that this one waits for may need the core
                else:
                    self.hub.poll(None if deadline is None else max(0.0, deadline - now))
                if inbox:
                    break
                now = time.monotonic()
                if deadline is not None and now >= deadline:
                    return None, False
        can_id, extended, data, stamp = inbox.popleft()
        message = can.Message(
            timestamp=stamp,
            arbitration_id=can_id,
            is_extended_id=extended,
            data=data,
            channel=self.channel_info,
        )
        return message, False

    def shutdown(self) -> None:
        if not self.closed:
            self.closed = True
            self.hub.stop()
        super().shutdown()
