"""The interop tier: phalanx's ARCOS code against software nobody here wrote, AMRISim (the
robot side, MobileSim's successor) and ARIA clients (AriaCoda's examples and our own
`aria_motion_check.cpp`), both built from their public sources (docs/INTEROP.md). The
tier runs when environment variables give them (CI's `.ci/run` sets them to the build it
is given), and skips with the reason otherwise:

- PHALANX_AMRISIM: the AMRISim binary (its resources are read from its directory);
  it runs headless under an Xvfb that the fixture starts (Debian: apt-get install xvfb).
- PHALANX_ARIA_EXAMPLES: AriaCoda's built `examples/` directory; its parent is the
  AriaCoda tree (include/, lib/libAria.so, params/) our own ARIA program is built against.
"""

from __future__ import annotations

import contextlib
import itertools
import math
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from phalanx.drivers.arcos_tracker import ArcosStats, SipTracker
from phalanx.protocols.arcos import (
    SIP_MOVING,
    SIP_STOPPED,
    SYNC2,
    Cmd,
    FrameParser,
    factors_for,
    frame,
    parse_sync2,
)
from phalanx.wire.transport import free_tcp_port

HERE = Path(__file__).resolve().parent
READY = re.compile(r"ready for a client to connect on TCP port (\d+)")


def _given(var: str, what: str) -> Path:
    value = os.environ.get(var)
    if not value:
        pytest.skip(f"{var} is not set: give {what} (docs/INTEROP.md: how to build it)")
    path = Path(value)
    if not path.exists():
        pytest.skip(f"{var}={value} does not exist")
    return path


def _stop(proc: subprocess.Popen[bytes] | subprocess.Popen[str]) -> None:
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(5.0)
        except subprocess.TimeoutExpired:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(5.0)


@dataclass
class Amrisim:
    """One AMRISim with one P3DX ("p3dx" model: DistConvFactor 0.485) in an empty map,
    exact odometry, logging every SIP it sends; on its own Xvfb display."""

    binary: Path
    log: Path
    port: int = 0
    xvfb: subprocess.Popen[bytes] | None = None
    proc: subprocess.Popen[bytes] | None = None
    _seen: int = 0

    def start(self, *extra: str) -> Amrisim:
        display = self._xvfb()
        env = {**os.environ, "AMRISIM": str(self.binary.parent), "DISPLAY": display}
        args = [str(self.binary), "--nomap", "-r", "p3dx:p3dx", "-p", str(free_tcp_port()),
                "--noninteractive", "--no-crash-restart", "--no-crash-debug",
                "--odom-error-mode", "none", "--log-movement-sent", "--log-file", str(self.log),
                *extra]  # fmt: skip
        self.proc = subprocess.Popen(
            args, env=env, cwd=self.binary.parent, start_new_session=True,
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        self.port = self.next_port(30.0)
        return self

    def _xvfb(self) -> str:
        if shutil.which("Xvfb") is None:
            pytest.skip("AMRISim needs an X display: install xvfb (apt-get install xvfb)")
        read, write = os.pipe()
        self.xvfb = subprocess.Popen(
            ["Xvfb", "-displayfd", str(write), "-screen", "0", "800x600x24", "-nolisten", "tcp"],
            pass_fds=(write,), start_new_session=True,
            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
        )  # fmt: skip
        os.close(write)
        with os.fdopen(read) as pipe:
            number = pipe.readline().strip()
        if not number:
            pytest.fail("Xvfb did not start")
        return f":{number}"

    def next_port(self, timeout_s: float = 15.0) -> int:
        """The port AMRISim listens on next: after a client leaves, it reopens its port or,
        when it cannot rebind it, the next one up (a reconnect must follow it)."""
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            text = self.log.read_text(errors="replace") if self.log.exists() else ""
            found = READY.findall(text)
            if len(found) > self._seen:
                self._seen = len(found)
                self.port = int(found[-1])
                time.sleep(0.2)
                return self.port
            if self.proc is not None and self.proc.poll() is not None:
                pytest.fail(f"AMRISim exited ({self.proc.returncode}): {text[-2000:]}")
            time.sleep(0.1)
        pytest.fail(f"AMRISim never got ready: {self.log.read_text(errors='replace')[-2000:]}")

    def sent_sips(self) -> list[tuple[int, int, int]]:
        """(x mm, y mm, th deg) of every SIP AMRISim logged sending (its own odometry)."""
        text = self.log.read_text(errors="replace")
        found = re.findall(r"converted from \((-?\d+),(-?\d+),(-?\d+)\)", text)
        return [(int(x), int(y), int(th)) for x, y, th in found]

    def pause(self, paused: bool) -> None:
        """SIGSTOP / SIGCONT the simulator: no SIPs, though its socket still takes bytes."""
        assert self.proc is not None
        os.kill(self.proc.pid, signal.SIGSTOP if paused else signal.SIGCONT)

    def close(self) -> None:
        if self.proc is not None:  # a simulator: nothing to save, no need to wait for it
            with contextlib.suppress(ProcessLookupError):
                os.killpg(self.proc.pid, signal.SIGKILL)
            self.proc.wait(5.0)
        if self.xvfb is not None:
            _stop(self.xvfb)


@pytest.fixture
def amrisim(tmp_path: Path) -> Iterator[Amrisim]:
    """A running AMRISim (not yet connected to)."""
    sim = Amrisim(_given("PHALANX_AMRISIM", "the AMRISim binary"), tmp_path / "amrisim.log")
    try:
        yield sim.start()
    finally:
        sim.close()


@dataclass
class Emulator:
    """`phalanx emulate p3dx --tcp PORT`, as a user runs it."""

    port: int
    proc: subprocess.Popen[str] | None = None
    output: list[str] = field(default_factory=list)

    def start(self) -> Emulator:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "phalanx", "emulate", "p3dx", "--tcp", str(self.port)],
            stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, start_new_session=True,
        )  # fmt: skip
        ready = threading.Event()

        def pump() -> None:
            assert self.proc is not None
            assert self.proc.stderr is not None
            for line in self.proc.stderr:
                self.output.append(line)
                if "emulated p3dx" in line:
                    ready.set()

        threading.Thread(target=pump, daemon=True).start()
        if not ready.wait(30.0):
            pytest.fail(f"phalanx emulate did not start: {''.join(self.output)}")
        return self

    def close(self) -> None:
        if self.proc is not None:
            _stop(self.proc)
            if self.proc.stderr is not None:
                self.proc.stderr.close()


@pytest.fixture
def emulator() -> Iterator[Emulator]:
    """A running `phalanx emulate p3dx --tcp` on a free port."""
    emu = Emulator(free_tcp_port())
    try:
        yield emu.start()
    finally:
        emu.close()


@dataclass(frozen=True)
class Aria:
    """AriaCoda: its tree (params, headers, libAria) and its built examples."""

    root: Path
    examples: Path
    libs: Path  # where the loader finds libAria under its soname

    @property
    def env(self) -> dict[str, str]:
        return {**os.environ, "ARIA": str(self.root), "LD_LIBRARY_PATH": str(self.libs)}

    def run(self, program: Path, port: int, timeout_s: float = 150.0) -> str:
        """Run an ARIA client against 127.0.0.1:`port`; its whole output."""
        proc = subprocess.run(
            [str(program), "-rh", "127.0.0.1", "-rrtp", str(port)],
            env=self.env, capture_output=True, text=True, timeout=timeout_s, check=False,
        )  # fmt: skip
        return proc.stdout + proc.stderr


@pytest.fixture(scope="session")
def aria(tmp_path_factory: pytest.TempPathFactory) -> Aria:
    """AriaCoda, from PHALANX_ARIA_EXAMPLES.

    ARIA's programs load `libAria.so.3` (its soname); a copied tree may hold that name as
    a broken link or a text file naming `libAria.so`, so the loader is pointed at a link
    of our own to the library itself.
    """
    examples = _given("PHALANX_ARIA_EXAMPLES", "AriaCoda's built examples/ directory")
    root = examples.resolve().parent
    library = root / "lib" / "libAria.so"
    if not library.exists():
        pytest.skip(f"no {library}: build AriaCoda first (docs/INTEROP.md)")
    libs = tmp_path_factory.mktemp("aria-libs")
    (libs / "libAria.so.3").symlink_to(library.resolve())
    return Aria(root, examples, libs)


@pytest.fixture(scope="session")
def aria_motion_check(aria: Aria, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Our ARIA client (tests/interop/aria_motion_check.cpp), built against AriaCoda."""
    compiler = shutil.which("g++")
    if compiler is None:
        pytest.skip("no g++ to build tests/interop/aria_motion_check.cpp")
    binary = tmp_path_factory.mktemp("aria") / "aria_motion_check"
    subprocess.run(
        [compiler, "-std=c++14", "-O1", f"-I{aria.root / 'include'}",
         str(HERE / "aria_motion_check.cpp"), f"-L{aria.libs}",
         str(aria.root / "lib" / "libAria.so"), "-lpthread", "-ldl", "-lrt", "-o", str(binary)],
        check=True, capture_output=True, timeout=300,
    )  # fmt: skip
    return binary


# -- recording what an ARIA client sends, and sending it again -------------------------


@dataclass(frozen=True)
class Sent:
    """One frame an ARIA client sent: when (s since it connected), in which of the robot's
    cycles (how many SIPs the robot had sent before it) and its body."""

    at_s: float
    cycle: int
    body: bytes


@dataclass
class Recording:
    """Every frame an ARIA client sent, and its output."""

    frames: list[Sent]
    output: str


def record(aria: Aria, program: Path, port: int) -> Recording:
    """Run `program` against 127.0.0.1:`port` through a proxy that notes, for each frame
    the program sends, its time and the robot's cycle (SIPs relayed to the program so far).
    """
    server = socket.create_server(("127.0.0.1", 0))
    frames: list[Sent] = []
    sips = [0]  # written by the robot's relay only

    def from_robot(src: socket.socket, dst: socket.socket) -> None:
        parser = FrameParser()
        while data := _recv(src):
            sips[0] += sum(body[0] in (SIP_STOPPED, SIP_MOVING) for body in parser.feed(data))
            dst.sendall(data)
        _finish(dst)

    def from_client(src: socket.socket, dst: socket.socket) -> None:
        parser, t0 = FrameParser(), time.monotonic()
        while data := _recv(src):
            now = time.monotonic() - t0
            frames.extend(Sent(now, sips[0], body) for body in parser.feed(data))
            dst.sendall(data)
        _finish(dst)

    def serve() -> None:
        client, _ = server.accept()
        upstream = socket.create_connection(("127.0.0.1", port))
        threads = [
            threading.Thread(target=from_client, args=(client, upstream)),
            threading.Thread(target=from_robot, args=(upstream, client)),
        ]
        for t in threads:
            t.start()
        for t in threads:
            t.join(200.0)

    proxy = threading.Thread(target=serve, daemon=True)
    proxy.start()
    output = aria.run(program, server.getsockname()[1])
    proxy.join(10.0)
    server.close()
    return Recording(frames, output)


def _recv(sock: socket.socket) -> bytes:
    try:
        return sock.recv(65536)
    except OSError:
        return b""


def _finish(dst: socket.socket) -> None:
    with contextlib.suppress(OSError):  # wakes the other relay's recv, sends the FIN
        dst.shutdown(socket.SHUT_RDWR)
    dst.close()


SETTLE_CYCLES = 10  # after the stream, 1 s of the robot's own time to come to rest
SIP_WAIT_S = 10.0  # a robot silent this long has stopped: the replay fails, never hangs


@dataclass(frozen=True)
class Reading:
    """One SIP as the driver reads it: the pose in the frame of the robot's first SIP
    (mm, mm, deg) and the speeds it reports (mm/s, deg/s)."""

    x_mm: float
    y_mm: float
    th_deg: float
    v_mmps: float
    w_degps: float


@dataclass(frozen=True)
class Replayed:
    """What a robot made of a replayed stream: one reading per SIP, in its own cycles."""

    sent: list[Sent]  # the frames it was sent, in order, in their cycles
    track: list[Reading]  # track[k - 1]: its SIP number k

    @property
    def pose(self) -> tuple[float, float, float]:
        """Where its SIPs say it ended (mm, mm, deg)."""
        end = self.track[-1]
        return end.x_mm, end.y_mm, end.th_deg


class _Client:
    """The client side of a replay: one connection, its SIPs read as the driver reads them."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port))
        self.parser = FrameParser()
        self.tracker = SipTracker(ArcosStats())
        self.track: list[Reading] = []
        self.t0 = time.monotonic()

    def read(self, timeout_s: float) -> None:
        self.sock.settimeout(max(timeout_s, 0.001))
        try:
            data = self.sock.recv(65536)
        except TimeoutError:
            return
        if not data:
            pytest.fail(f"the robot closed the replay's connection after {len(self.track)} SIPs")
        for body in self.parser.feed(data):
            if body[0] == SYNC2 and len(body) > 3:
                self.tracker.factors = factors_for(parse_sync2(body)[2])
            elif self.tracker.take(body, byte_time_s=0.0) is not None:
                self.track.append(_reading(self.tracker))

    def until_sip(self, count: int) -> None:
        """Read until the robot's SIP number `count` has come."""
        deadline = time.monotonic() + SIP_WAIT_S
        while len(self.track) < count:
            left = deadline - time.monotonic()
            if left <= 0:
                pytest.fail(
                    f"no SIP for {SIP_WAIT_S} s: {len(self.track)} of {count}, {self.parser.stats}"
                )
            self.read(min(left, 0.05))

    def until_time(self, at_s: float) -> None:
        """Read until `at_s` seconds after connecting."""
        while (left := self.t0 + at_s - time.monotonic()) > 0:
            self.read(min(left, 0.05))

    def close(self) -> None:
        self.sock.close()


def _reading(tracker: SipTracker) -> Reading:
    odometry = tracker.odometry
    assert odometry is not None  # set by the SIP just taken
    pose, twist = odometry.pose, odometry.twist
    return Reading(
        pose.x_m * 1000.0, pose.y_m * 1000.0, math.degrees(pose.theta_rad),
        twist.v_mps * 1000.0, math.degrees(twist.omega_radps),
    )  # fmt: skip


def replay(frames: list[Sent], port: int) -> Replayed:
    """Send `frames` to 127.0.0.1:`port`, each in its cycle: right after the robot's SIP
    number `cycle` (the handshake, before any SIP, at its recorded time), up to the final
    CLOSE; then 1 s of the robot's cycles to settle. Its SIPs, read all along, are the
    robot's own account of each of its cycles (AMRISim's, the very SIPs its
    `--log-movement-sent` logs).

    Paced by the robot's own SIPs, not by our clock: a loaded machine stretches a robot's
    cycles (AMRISim's simulation steps a fixed 100 ms each, however late they run), and a
    replay on our clock would give two robots the same command after different amounts
    of their own time.
    """
    client = _Client(port)
    try:
        stream = list(itertools.takewhile(lambda s: not _closes(s), frames))
        for sent in stream:
            if sent.cycle == 0:
                client.until_time(sent.at_s)
            else:
                client.until_sip(sent.cycle)
            client.sock.sendall(frame(sent.body))
        client.until_sip(max((s.cycle for s in stream), default=0) + SETTLE_CYCLES)
    finally:
        client.close()
    return Replayed(stream, client.track)


def _closes(sent: Sent) -> bool:
    """CLOSE, the stream's end (it shares its number with SYNC2, sent before any SIP)."""
    return sent.body[0] == Cmd.CLOSE and sent.cycle > 0


@pytest.fixture
def recorder() -> Callable[[Aria, Path, int], Recording]:
    """`record(aria, program, port)` (a fixture so tests need not import this module)."""
    return record


@pytest.fixture
def replayer() -> Callable[[list[Sent], int], Replayed]:
    """`replay(frames, port)`."""
    return replay
