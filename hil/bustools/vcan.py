"""`hil bus up/down`: create or remove a virtual SocketCAN interface (vcan) where the kernel
has one; elsewhere say so in one `hil: error:` line and point at the loopback hub (exit 1).

Support is detected without side effects: opening (and closing) an AF_CAN raw socket tells
whether the kernel has SocketCAN; the vcan driver itself is only known once `ip link add`
runs, whose own message is passed on if it fails.
"""

from __future__ import annotations

import shutil
import socket
import subprocess

from hil.errors import BusError

LOOPBACK_HINT = (
    "use the loopback hub instead: `hil bus serve` in one terminal, then `--bus loopback` "
    "(or python-can interface socketcand, host 127.0.0.1, port 29536)"
)


def socketcan_available() -> bool:
    """True if this kernel lets a process open a CAN raw socket."""
    family = getattr(socket, "AF_CAN", None)
    if family is None:
        return False
    try:
        probe = socket.socket(family, socket.SOCK_RAW, socket.CAN_RAW)
    except OSError:
        return False
    probe.close()
    return True


def interface_exists(name: str) -> bool:
    try:
        socket.if_nametoindex(name)
    except OSError:
        return False
    return True


def _ip(*args: str) -> None:
    ip = shutil.which("ip")
    if ip is None:
        raise BusError("the `ip` command (iproute2) is needed to manage vcan interfaces")
    done = subprocess.run([ip, *args], capture_output=True, text=True, check=False)
    if done.returncode != 0:
        reason = (done.stderr or done.stdout).strip().splitlines()
        raise BusError(f"ip {' '.join(args)}: {reason[0] if reason else 'failed'}")


def up(name: str) -> str:
    """Create (if needed) and bring up vcan `name`; returns what was done."""
    if interface_exists(name):
        _ip("link", "set", "up", name)
        return f"{name} exists; set up"
    _ip("link", "add", "dev", name, "type", "vcan")
    _ip("link", "set", "up", name)
    return f"{name} created and up; use --bus socketcan:{name}"


def down(name: str) -> str:
    if not interface_exists(name):
        return f"{name} does not exist; nothing to do"
    _ip("link", "delete", "dev", name)
    return f"{name} removed"
