"""The robot's end of an ARCOS link for the emulator: a pseudo-terminal (clients open its
device with pyserial) or a TCP port serving one client at a time (the MobileSim/AMRISim
convention, port 8101).
"""

from __future__ import annotations

import contextlib
import os
import select
import socket
import termios
import tty
from typing import Protocol


class Link(Protocol):
    """A byte pipe to the one connected client."""

    def read(self, timeout_s: float) -> bytes | None:
        """Bytes received (b"" if none in time); None when the client is gone."""
        ...

    def write(self, data: bytes) -> None:
        """Send bytes (dropped when no client is connected)."""
        ...

    def drop_client(self) -> None:
        """Disconnect the current client (the link stays usable for the next one)."""
        ...

    def close(self) -> None:
        """Release everything."""
        ...


class PtyLink:
    """The robot's end of a pseudo-terminal; clients open `device` with pyserial."""

    def __init__(self) -> None:
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        attrs = termios.tcgetattr(self._slave)
        attrs[3] &= ~termios.ECHO
        termios.tcsetattr(self._slave, termios.TCSANOW, attrs)
        self.device = os.ttyname(self._slave)
        self._closed = False

    def read(self, timeout_s: float) -> bytes | None:
        """Bytes from the client side."""
        if self._closed:
            return None
        ready, _, _ = select.select([self._master], [], [], timeout_s)
        if not ready:
            return b""
        try:
            return os.read(self._master, 4096)
        except OSError:
            return b""  # no client has the device open: nothing to read

    def write(self, data: bytes) -> None:
        """Bytes to the client side."""
        if not self._closed:
            with contextlib.suppress(OSError):
                os.write(self._master, data)

    def drop_client(self) -> None:
        """A pty cannot be unplugged without removing it: closing it is the unplug."""
        self.close()

    def close(self) -> None:
        """Close both ends (the device disappears)."""
        if not self._closed:
            self._closed = True
            for fd in (self._master, self._slave):
                with contextlib.suppress(OSError):
                    os.close(fd)


class TcpLink:
    """A listening TCP socket that serves one client at a time (MobileSim style)."""

    def __init__(self, port: int = 8101, host: str = "127.0.0.1") -> None:
        self._server = socket.create_server((host, port), reuse_port=False)
        self._server.setblocking(False)
        self.port = self._server.getsockname()[1]
        self.host = host
        self._client: socket.socket | None = None
        self._closed = False

    def read(self, timeout_s: float) -> bytes | None:
        """Accept a client if none; bytes from it."""
        if self._closed:
            return None
        sock = self._client or self._server
        ready, _, _ = select.select([sock], [], [], timeout_s)
        if not ready:
            return b""
        if self._client is None:
            with contextlib.suppress(BlockingIOError):
                self._client, _ = self._server.accept()
                self._client.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            return b""
        try:
            data = self._client.recv(4096)
        except OSError:
            data = b""
        if not data:
            self.drop_client()
            return None
        return data

    def write(self, data: bytes) -> None:
        """Send to the client, if any."""
        if self._client is not None:
            try:
                self._client.sendall(data)
            except OSError:
                self.drop_client()

    def drop_client(self) -> None:
        """Close the client's connection; wait for the next one."""
        if self._client is not None:
            with contextlib.suppress(OSError):
                self._client.close()
            self._client = None

    def close(self) -> None:
        """Close the client and the listening socket."""
        if not self._closed:
            self._closed = True
            self.drop_client()
            with contextlib.suppress(OSError):
                self._server.close()
