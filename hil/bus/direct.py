"""A synchronous in-process CAN bus pair: the controller and the plant in one thread.

`direct_pair()` returns two python-can buses. What the controller's end sends is handed at once
to the plant's handler (the plant reacts inside the controller's `send`); what the plant sends
waits in the controller's inbox until the controller receives it. The controller, as SYNC
producer, drives the whole run from its own loop, and no frame ever crosses a thread: in
lockstep every frame a cycle needs is in the inbox by the time the controller looks for it.

Frames are copied on delivery (as a real bus would), and the order of delivery is the order of
sending, so a run over this pair gives the same CAN log, byte for byte, as over python-can's
virtual bus with the controller in a thread.
"""

from __future__ import annotations

import time
from collections import deque
from collections.abc import Callable

import can

from rigbus.canbus import c_messages, unchecked_message

Handler = Callable[[can.Message], None]


class DirectBus(can.BusABC):
    """One end of a direct pair; see the module docstring."""

    def __init__(self, name: str, **kwargs: object) -> None:
        self.channel_info = f"direct:{name}"
        self.inbox: deque[can.Message] = deque()
        self.peer: DirectBus | None = None
        self.handler: Handler | None = None
        made_in_c = c_messages()  # the copy of a can.Message made in C (None for any other)
        self._copy_in_c = _no_copy if made_in_c is None else made_in_c.copy_message
        super().__init__(channel=name, **kwargs)  # type: ignore[arg-type]

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        peer = self.peer
        if peer is None:
            raise can.CanOperationError(f"{self.channel_info}: the other end is shut down")
        copy = self._copy_in_c(msg, peer.channel_info)
        if copy is None:
            copy = _copy(msg, peer.channel_info)
        if peer.handler is not None:
            peer.handler(copy)
        else:
            peer.inbox.append(copy)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        """python-can's `BusABC.recv`; a frame waiting and no filters set (the lockstep case:
        the controller reads a SYNC's frames back to back) is handed over without its loop."""
        if self.inbox and self._filters is None:
            return self.inbox.popleft()
        return super().recv(timeout)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self.inbox:
            return self.inbox.popleft(), False
        # nothing can arrive while this thread waits: waiting out the timeout is all that is left
        if timeout:
            time.sleep(timeout)
        return None, False

    def shutdown(self) -> None:
        if self.peer is not None:
            self.peer.peer = None
            self.peer = None
        super().shutdown()


def _copy(msg: can.Message, channel: str) -> can.Message:
    """`msg` as delivered on `channel`: every field the same, its data a copy of its own."""
    return unchecked_message(
        msg.timestamp, msg.arbitration_id, msg.is_extended_id, msg.is_remote_frame,
        msg.is_error_frame, channel, msg.dlc, bytearray(msg.data), msg.is_fd, msg.is_rx,
        msg.bitrate_switch, msg.error_state_indicator,
    )  # fmt: skip


def _no_copy(msg: can.Message, channel: str) -> None:
    """No C copier: `_copy` copies."""


def direct_pair(name: str = "softhil") -> tuple[DirectBus, DirectBus]:
    """(plant end, controller end): set the plant end's `handler` before the controller sends."""
    plant, controller = DirectBus(f"{name}/plant"), DirectBus(f"{name}/controller")
    plant.peer, controller.peer = controller, plant
    return plant, controller
