"""The interop tier: phalanx's ARCOS code against software nobody here wrote, AMRISim (the
robot side, MobileSim's successor) and ARIA clients (AriaCoda's examples and our own
`aria_motion_check.cpp`). Both are built by hand from their public sources
(docs/INTEROP.md); the tier runs only when environment variables give them, and skips
with the reason otherwise (CI builds neither):

- PHALANX_AMRISIM: the AMRISim binary (its resources are read from its directory);
  it runs headless under an Xvfb that the fixture starts (Debian: apt-get install xvfb).
- PHALANX_ARIA_EXAMPLES: AriaCoda's built `examples/` directory; its parent is the
  AriaCoda tree (include/, lib/libAria.so, params/) our own ARIA program is built against.
"""

from __future__ import annotations

import contextlib
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
from phalanx.protocols.arcos import SYNC2, FrameParser, factors_for, frame, parse_sync2
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

    @property
    def env(self) -> dict[str, str]:
        lib = str(self.root / "lib")
        return {**os.environ, "ARIA": str(self.root), "LD_LIBRARY_PATH": lib}

    def run(self, program: Path, port: int, timeout_s: float = 150.0) -> str:
        """Run an ARIA client against 127.0.0.1:`port`; its whole output."""
        proc = subprocess.run(
            [str(program), "-rh", "127.0.0.1", "-rrtp", str(port)],
            env=self.env, capture_output=True, text=True, timeout=timeout_s, check=False,
        )  # fmt: skip
        return proc.stdout + proc.stderr


@pytest.fixture(scope="session")
def aria() -> Aria:
    """AriaCoda, from PHALANX_ARIA_EXAMPLES."""
    examples = _given("PHALANX_ARIA_EXAMPLES", "AriaCoda's built examples/ directory")
    root = examples.resolve().parent
    if not (root / "lib" / "libAria.so").exists():
        pytest.skip(f"no {root / 'lib' / 'libAria.so'}: build AriaCoda first (docs/INTEROP.md)")
    return Aria(root, examples)


@pytest.fixture(scope="session")
def aria_motion_check(aria: Aria, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Our ARIA client (tests/interop/aria_motion_check.cpp), built against AriaCoda."""
    compiler = shutil.which("g++")
    if compiler is None:
        pytest.skip("no g++ to build tests/interop/aria_motion_check.cpp")
    binary = tmp_path_factory.mktemp("aria") / "aria_motion_check"
    subprocess.run(
        [compiler, "-std=c++14", "-O1", f"-I{aria.root / 'include'}",
         str(HERE / "aria_motion_check.cpp"), f"-L{aria.root / 'lib'}", "-lAria",
         "-lpthread", "-ldl", "-lrt", "-o", str(binary)],
        check=True, capture_output=True, timeout=300,
    )  # fmt: skip
    return binary


# -- recording what an ARIA client sends, and sending it again -------------------------


@dataclass
class Recording:
    """Every frame an ARIA client sent (seconds since it connected, body), and its output."""

    frames: list[tuple[float, bytes]]
    output: str


def record(aria: Aria, program: Path, port: int) -> Recording:
    """Run `program` against 127.0.0.1:`port` through a proxy that timestamps its frames."""
    server = socket.create_server(("127.0.0.1", 0))
    frames: list[tuple[float, bytes]] = []

    def relay(src: socket.socket, dst: socket.socket, parser: FrameParser | None) -> None:
        t0 = time.monotonic()
        while data := _recv(src):
            if parser is not None:
                now = time.monotonic() - t0
                frames.extend((now, body) for body in parser.feed(data))
            dst.sendall(data)
        with contextlib.suppress(OSError):  # wakes the other relay's recv, sends the FIN
            dst.shutdown(socket.SHUT_RDWR)
        dst.close()

    def serve() -> None:
        client, _ = server.accept()
        upstream = socket.create_connection(("127.0.0.1", port))
        threads = [
            threading.Thread(target=relay, args=(client, upstream, FrameParser())),
            threading.Thread(target=relay, args=(upstream, client, None)),
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


def replay(frames: list[tuple[float, bytes]], port: int) -> tuple[float, float, float]:
    """Send `frames` to 127.0.0.1:`port` at their recorded times (up to the final CLOSE);
    the robot's end pose as its SIPs tell it, in the frame of its first SIP (mm, mm, deg),
    read as the driver reads it (`SipTracker`).
    """
    tracker = SipTracker(ArcosStats())
    parser = FrameParser()
    sock = socket.create_connection(("127.0.0.1", port))
    sock.settimeout(0.005)
    t0 = time.monotonic()

    def drain() -> None:
        try:
            data = sock.recv(65536)
        except TimeoutError:
            return
        for body in parser.feed(data):
            if body[0] == SYNC2 and len(body) > 3:
                tracker.factors = factors_for(parse_sync2(body)[2])
            else:
                tracker.take(body, byte_time_s=0.0)

    try:
        for at_s, body in frames:
            if body[0] == 2 and at_s > 1.0:  # CLOSE (after the sync's SYNC2): the end
                break
            while time.monotonic() - t0 < at_s:
                drain()
            sock.sendall(frame(body))
        settle = time.monotonic() + 1.0
        while time.monotonic() < settle:
            drain()
    finally:
        sock.close()
    assert tracker.odometry is not None, f"no SIP came back from port {port}: {parser.stats}"
    pose = tracker.odometry.pose
    return pose.x_m * 1000.0, pose.y_m * 1000.0, math.degrees(pose.theta_rad)


@pytest.fixture
def recorder() -> Callable[[Aria, Path, int], Recording]:
    """`record(aria, program, port)` (a fixture so tests need not import this module)."""
    return record


@pytest.fixture
def replayer() -> Callable[[list[tuple[float, bytes]], int], tuple[float, float, float]]:
    """`replay(frames, port)`."""
    return replay
