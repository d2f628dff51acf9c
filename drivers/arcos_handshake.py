"""Opening an ARCOS connection as ARIA does (AriaCoda `src/ArRobot.cpp`,
`ArRobotConnector`): SYNC0, SYNC1, SYNC2 (whose reply names the robot and its subtype),
OPEN, STOP, PULSE, CONFIG (the robot's configuration packet, awaited as ARIA does for up
to a second), ENABLE, SONAR, then the first SIP.

`open_connection` does all of it on a link of its own and hands back the open link with
what it learnt; it holds no lock and touches no driver state, so a reconnect runs on the
driver's reader thread while the control thread keeps reading and commanding.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass, field

from phalanx.core.errors import DriverError, DriverTimeout, DriverUnavailable, ProtocolError
from phalanx.drivers.arcos_link import Link, open_link
from phalanx.protocols.arcos import (
    CONFIG_PAC,
    SIP_MOVING,
    SIP_STOPPED,
    SYNC0,
    SYNC1,
    SYNC2,
    Cmd,
    FrameParser,
    ParserStats,
    RobotConfig,
    command,
    decode_config,
    parse_sync2,
)


@dataclass(frozen=True)
class Identity:
    """Who answered: SYNC2's name and subtype, and CONFIG's serial number ("" if none)."""

    name: str
    subtype: str
    serial: str = ""

    def same_robot(self, other: Identity) -> bool:
        """Whether `other` can be this robot (a missing serial number matches any)."""
        serials = self.serial and other.serial
        return (self.name, self.subtype) == (other.name, other.subtype) and (
            not serials or self.serial == other.serial
        )


@dataclass(frozen=True)
class HandshakeOptions:
    """What the handshake sends and how long it waits (from the driver's settings)."""

    connect_timeout_s: float
    sync_retries: int
    config_timeout_s: float
    baud: int
    sonar: bool
    enable: bool  # False while the driver's E-stop latch holds: motors stay disabled


@dataclass
class Connection:
    """An open link after the handshake, and what the robot said during it."""

    link: Link
    address: str
    parser: FrameParser
    identity: Identity
    config: RobotConfig | None
    frames: list[bytes] = field(default_factory=list)  # after CONFIG: the first SIP(s)


def open_connection(
    address: str,
    options: HandshakeOptions,
    *,
    tcp: bool,
    stats: ParserStats | None = None,
    abort: threading.Event | None = None,
) -> Connection:
    """Open `address` (host:port if `tcp`, else a serial device) and run the handshake.

    DriverError (DriverUnavailable, DriverTimeout) if the robot cannot be reached or does
    not answer, or `abort` is set meanwhile (the driver is closing); the link is closed
    again then.
    """
    link = open_link(
        port=None if tcp else address,
        tcp=address if tcp else None,
        baud=options.baud,
        timeout_s=options.connect_timeout_s,
    )
    parser = FrameParser(stats=stats or ParserStats())
    link = _Abortable(link, abort or threading.Event(), address)
    try:
        name, subtype = _sync(link, parser, address, options)
        for step in (command(Cmd.OPEN), command(Cmd.STOP), command(Cmd.PULSE)):
            link.write(step)
        link.write(command(Cmd.CONFIG))
        config, frames = _await_config(link, parser, options.config_timeout_s)
        link.write(command(Cmd.ENABLE, 1 if options.enable else 0))
        link.write(command(Cmd.SONAR, 1 if options.sonar else 0))
        frames += _await_sip(link, parser, address, options.connect_timeout_s, frames)
    except DriverError:
        link.close()
        raise
    identity = Identity(name, subtype, config.serial if config is not None else "")
    return Connection(link.link, address, parser, identity, config, frames)


class _Abortable:
    """A link whose reads and writes fail once `abort` is set."""

    def __init__(self, link: Link, abort: threading.Event, address: str) -> None:
        self.link, self.abort, self.address = link, abort, address
        self.byte_time_s = link.byte_time_s

    def _check(self) -> None:
        if self.abort.is_set():
            raise DriverUnavailable(f"connecting to {self.address} abandoned: driver closing")

    def read(self, timeout_s: float) -> bytes:
        self._check()
        return self.link.read(timeout_s)

    def write(self, data: bytes) -> None:
        self._check()
        self.link.write(data)

    def close(self) -> None:
        self.link.close()


def _sync(
    link: Link, parser: FrameParser, address: str, options: HandshakeOptions
) -> tuple[str, str]:
    for _attempt in range(options.sync_retries):
        names = _try_sync(link, parser, options.connect_timeout_s / 3)
        if names is not None:
            return names
        link.write(command(Cmd.CLOSE))  # an old connection may be open: close, resync
        time.sleep(0.1)
    raise DriverTimeout(f"no ARCOS sync from {address}")


def _try_sync(link: Link, parser: FrameParser, per_step_s: float) -> tuple[str, str] | None:
    for step in (SYNC0, SYNC1, SYNC2):
        link.write(command(step))
        body = _await_frame(link, parser, step, per_step_s)
        if body is None:
            return None
        if step == SYNC2:
            name, _type, subtype = parse_sync2(body)
            return name, subtype
    return None


def _await_frame(link: Link, parser: FrameParser, wanted: int, timeout_s: float) -> bytes | None:
    deadline = time.monotonic() + timeout_s
    while (left := deadline - time.monotonic()) > 0:
        for body in parser.feed(link.read(min(left, 0.05))):
            if body[0] == wanted:
                return body
            if body[0] in (SIP_STOPPED, SIP_MOVING):
                return None  # SIPs during sync: an old connection is still open
    return None


def _await_config(
    link: Link, parser: FrameParser, timeout_s: float
) -> tuple[RobotConfig | None, list[bytes]]:
    """The CONFIG packet (None if none came in time: the driver goes on without the
    robot's limits, as ARIA does) and any other frames that came meanwhile.
    """
    frames: list[bytes] = []
    deadline = time.monotonic() + timeout_s
    while (left := deadline - time.monotonic()) > 0:
        for body in parser.feed(link.read(min(left, 0.05))):
            if body[0] != CONFIG_PAC:
                frames.append(body)
                continue
            try:
                return decode_config(body), frames
            except ProtocolError:
                continue
    return None, frames


def _await_sip(
    link: Link, parser: FrameParser, address: str, timeout_s: float, seen: list[bytes]
) -> list[bytes]:
    if any(b[0] in (SIP_STOPPED, SIP_MOVING) for b in seen):
        return []
    frames: list[bytes] = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        for body in parser.feed(link.read(0.05)):
            frames.append(body)
            if body[0] in (SIP_STOPPED, SIP_MOVING):
                return frames
    raise DriverTimeout(f"robot at {address} opened but sends no SIPs")
