"""The byte links under the `arcos` backend: a serial port (pyserial) or TCP (MobileSim
convention, port 8101). Both raise `DriverUnavailable` when the link is lost, which the
driver's reader turns into a reconnect.
"""

from __future__ import annotations

import contextlib
import os
import socket
import termios
from typing import Protocol

import serial

from phalanx.core.errors import DriverUnavailable


class Link(Protocol):
    """A byte stream to the robot."""

    # How long one byte takes on the wire: a SIP's pose is this much per byte older than
    # the moment its last byte arrived.
    byte_time_s: float

    def read(self, timeout_s: float) -> bytes:
        """What has arrived, waiting up to `timeout_s` for the first byte (b"" if none)."""
        ...

    def write(self, data: bytes) -> None:
        """Send `data`."""
        ...

    def close(self) -> None:
        """Release the port or socket; safe to call twice."""
        ...


def byte_time_s(port: str, baud: int) -> float:
    """How long one byte takes on serial `port` at `baud` (8N1: 10 bits a byte).

    Zero for a pseudo-terminal (an emulator): it moves bytes at memory speed whatever
    its nominal baud rate.
    """
    return 0.0 if os.path.realpath(port).startswith("/dev/pts/") else 10.0 / baud


def open_link(*, port: str | None, tcp: str | None, baud: int, timeout_s: float) -> Link:
    """The serial `port` at `baud` if given, else TCP to `tcp` ("host:port")."""
    if port is not None:
        return SerialLink(port, baud)
    if tcp is None:
        raise DriverUnavailable("no link: give a serial port or a TCP address")
    return TcpLink(tcp, timeout_s)


class SerialLink:
    """A serial port, 8N1."""

    def __init__(self, port: str, baud: int) -> None:
        self.byte_time_s = byte_time_s(port, baud)
        try:
            self._serial = serial.Serial(port, baud, timeout=0.0, write_timeout=1.0)
        except (serial.SerialException, OSError) as exc:
            raise DriverUnavailable(f"cannot open serial port {port}: {exc}") from exc

    def read(self, timeout_s: float) -> bytes:
        """What has arrived, waiting up to `timeout_s` for the first byte."""
        try:
            if self._serial.timeout != timeout_s:
                self._serial.timeout = timeout_s  # reconfigures the port: may fail too
            first = self._serial.read(1)
            return first + self._serial.read(self._serial.in_waiting) if first else b""
        except (serial.SerialException, OSError, TypeError, termios.error) as exc:
            raise DriverUnavailable(f"serial link lost: {exc}") from exc

    def write(self, data: bytes) -> None:
        """Send `data`."""
        try:
            self._serial.write(data)
        except (serial.SerialException, OSError) as exc:
            raise DriverUnavailable(f"serial link lost: {exc}") from exc

    def close(self) -> None:
        """Close the port."""
        with contextlib.suppress(serial.SerialException, OSError):
            self._serial.close()


class TcpLink:
    """A TCP connection (Nagle off: commands are small and due now)."""

    byte_time_s = 0.0

    def __init__(self, address: str, timeout_s: float) -> None:
        host, _, port = address.rpartition(":")
        try:
            self._sock = socket.create_connection((host, int(port)), timeout=timeout_s)
        except OSError as exc:
            raise DriverUnavailable(f"cannot connect to {address}: {exc}") from exc
        self._sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    def read(self, timeout_s: float) -> bytes:
        """What has arrived, waiting up to `timeout_s`."""
        try:
            self._sock.settimeout(timeout_s)
            data = self._sock.recv(4096)
        except TimeoutError:
            return b""
        except OSError as exc:
            raise DriverUnavailable(f"TCP link lost: {exc}") from exc
        if not data:
            raise DriverUnavailable("TCP link closed by the robot")
        return data

    def write(self, data: bytes) -> None:
        """Send `data`."""
        try:
            self._sock.sendall(data)
        except OSError as exc:
            raise DriverUnavailable(f"TCP link lost: {exc}") from exc

    def close(self) -> None:
        """Close the socket."""
        with contextlib.suppress(OSError):
            self._sock.close()
