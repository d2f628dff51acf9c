"""AMRISim as a run's robots: simulated P3DX firmware nobody here wrote, driven exactly as
real robots are, through the `arcos` driver over TCP.

- The scenario's world becomes an AMRISim map (`amrisim_map`: ARIA's map format, its
  obstacles as wall lines, a circle as a polygon drawn round it).
- One AMRISim runs every robot (`-r p3dx:<id>`), headless under an Xvfb of its own
  (AMRISim needs an X display even without its window). It gives robot after robot, in
  the order of their names, the TCP ports from `-p` on (`amrisim_ports`).
- The robots start parked in a row off the map; each robot's driver puts it at its
  scenario start pose when it connects (`place_at`: SIM_SET_POSE, which leaves the
  odometry alone) and asks for its true pose (SIMSTAT) for the run's record.

The binary is the user's build of AMRISim (docs/INTEROP.md says how): `PHALANX_AMRISIM`
or `phalanx up --amrisim`; its resources are read from the binary's folder.
"""

from __future__ import annotations

import math
import os
import shutil
import signal
import socket
import subprocess
from dataclasses import dataclass
from pathlib import Path
from typing import Final, Literal, get_args

from phalanx.core.config import Scenario, WorldConfig
from phalanx.core.errors import ConfigError
from phalanx.core.scenarios import resolve_world
from phalanx.wire.transport import free_tcp_port

AMRISIM_ENV: Final = "PHALANX_AMRISIM"
OdometryError = Literal["none", "random_init", "random_each_update", "constant"]
ODOMETRY_ERRORS: Final[tuple[OdometryError, ...]] = get_args(OdometryError)
CIRCLE_SIDES: Final = 32  # a circle's polygon (drawn round it: never smaller)
PARKING_GAP_M: Final = 20.0  # robots wait this far beyond everything else in the map
XVFB_TIMEOUT_S: Final = 10.0
_PR_SET_PDEATHSIG: Final = 1


def amrisim_binary(given: Path | None) -> Path:
    """The AMRISim binary: `given`, else `$PHALANX_AMRISIM`; ConfigError saying how to
    get one when neither names an executable file.
    """
    value = given or (Path(os.environ[AMRISIM_ENV]) if os.environ.get(AMRISIM_ENV) else None)
    if value is None:
        raise ConfigError(
            f"no AMRISim: give its binary with --amrisim PATH or {AMRISIM_ENV}=PATH "
            "(build it from github.com/reedhedges/AMRISim as docs/INTEROP.md says)"
        )
    if not (value.is_file() and os.access(value, os.X_OK)):
        raise ConfigError(f"AMRISim binary {value}: no such executable file")
    return value


def odometry_error(value: str) -> OdometryError:
    """`value` as AMRISim's odometry error mode (ConfigError naming the modes if not one)."""
    for mode in ODOMETRY_ERRORS:
        if value == mode:
            return mode
    raise ConfigError(f"AMRISim odometry error: one of {', '.join(ODOMETRY_ERRORS)}, not {value!r}")


def _polygons(world: WorldConfig) -> list[list[tuple[float, float]]]:
    """Every obstacle of `world` as a closed outline (m)."""
    outlines = [list(p.vertices_m) for p in world.polygons]
    reach = 1.0 / math.cos(math.pi / CIRCLE_SIDES)  # a vertex radius whose sides touch it
    for c in world.circles:
        outlines.append([
            (c.x_m + reach * c.radius_m * math.cos(a), c.y_m + reach * c.radius_m * math.sin(a))
            for a in (2 * math.pi * (i + 0.5) / CIRCLE_SIDES for i in range(CIRCLE_SIDES))
        ])  # fmt: skip
    return outlines


def amrisim_map(scenario: Scenario) -> str:
    """The scenario's world as an ARIA map: every obstacle's outline as wall lines (mm),
    the bounds wide enough for the robots' starts and their parking row too.
    """
    lines = []
    for outline in _polygons(resolve_world(scenario.world)):
        for (ax, ay), (bx, by) in zip(outline, outline[1:] + outline[:1], strict=True):
            lines.append(tuple(round(v * 1000.0) for v in (ax, ay, bx, by)))
    xs = [v for a, _, b, _ in lines for v in (a, b)] or [0]
    ys = [v for _, a, _, b in lines for v in (a, b)] or [0]
    park_x, park_y = parking(scenario)
    xs += [round(r.start.x_m * 1000.0) for r in scenario.robots] + [round(park_x * 1000.0)]
    ys += [round(r.start.y_m * 1000.0) for r in scenario.robots] + [round(park_y * 1000.0)]
    ys.append(round((park_y - len(scenario.robots)) * 1000.0))
    low, high = f"{min(xs) - 1000} {min(ys) - 1000}", f"{max(xs) + 1000} {max(ys) + 1000}"
    head = ["2D-Map", f"MinPos: {low}", f"MaxPos: {high}"]
    if lines:  # (ARIA's reader refuses "NumLines: 0": a map without walls has no count)
        head += [f"LineMinPos: {low}", f"LineMaxPos: {high}", f"NumLines: {len(lines)}"]
    head.append(f'MapInfo: Name="phalanx: {_quoted(scenario.name)}"')
    walls = ["LINES", *(" ".join(map(str, line)) for line in lines)] if lines else []
    return "\n".join([*head, *walls, "DATA", ""])


def _quoted(text: str) -> str:
    return "".join(c for c in text if c.isalnum() or c in " ._-")[:64]


def parking(scenario: Scenario) -> tuple[float, float]:
    """Where the first robot waits to be placed (m); the others in a row 1 m apart
    below it, as AMRISim lines them up: clear of every obstacle and start.
    """
    world = resolve_world(scenario.world)
    xs = [r.start.x_m for r in scenario.robots]
    xs += [c.x_m + c.radius_m for c in world.circles]
    xs += [x for p in world.polygons for x, _ in p.vertices_m]
    return max(xs) + PARKING_GAP_M, 0.0


def free_port_run(count: int, tries: int = 50) -> int:
    """The first of `count` TCP ports in a row free on 127.0.0.1 right now."""
    for _ in range(tries):
        base = free_tcp_port()
        if base + count <= 65536 and all(_free(base + i) for i in range(1, count)):
            return base
    raise ConfigError(f"found no {count} free TCP ports in a row on 127.0.0.1")


def _free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        try:
            sock.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def amrisim_ports(robot_ids: tuple[str, ...], base_port: int) -> dict[str, int]:
    """The TCP port of each robot: AMRISim opens them from `base_port` on, robot after
    robot in the order of their names (it keeps its robots in a map sorted by name).
    """
    return {rid: base_port + i for i, rid in enumerate(sorted(robot_ids))}


@dataclass(frozen=True)
class AmrisimCommand:
    """How to run one AMRISim for a scenario's robots."""

    binary: Path
    map_path: Path
    log_path: Path
    base_port: int
    odometry_error: OdometryError = "none"

    def argv(self, scenario: Scenario) -> list[str]:
        """Its command line: the robots parked, on loopback only, no discovery, no
        dialogs, no restarts.
        """
        x_m, y_m = parking(scenario)
        robots = [arg for r in scenario.robots for arg in ("-r", f"p3dx:{r.id}")]
        return [
            str(self.binary), "-m", str(self.map_path), *robots, "-p", str(self.base_port),
            "--start", f"{round(x_m * 1000)},{round(y_m * 1000)},0",
            "--odom-error-mode", self.odometry_error, "-l", str(self.log_path),
            "--bind-to-address", "127.0.0.1", "--noninteractive", "--no-crash-restart",
            "--no-crash-debug", "--no-network-discovery",
        ]  # fmt: skip

    def env(self, display: str) -> dict[str, str]:
        """Its environment: its resources beside the binary, the display to draw on."""
        return {**os.environ, "AMRISIM": str(self.binary.parent), "DISPLAY": display}


def die_with_us() -> None:
    """In a child before it runs (Linux): SIGTERM when the process that started it dies,
    so no simulator or X server outlives a killed `phalanx up`.
    """
    import ctypes

    try:
        ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM, 0, 0, 0)
    except (OSError, AttributeError):
        return


class Xvfb:
    """A virtual X display of our own (`Xvfb -displayfd`); a context manager."""

    def __init__(self) -> None:
        self.process: subprocess.Popen[bytes] | None = None
        self.display = ""

    def __enter__(self) -> Xvfb:
        if shutil.which("Xvfb") is None:
            raise ConfigError("AMRISim needs an X display: install Xvfb (apt-get install xvfb)")
        read, write = os.pipe()
        self.process = subprocess.Popen(  # noqa: S603 - the X server, our arguments
            ["Xvfb", "-displayfd", str(write), "-screen", "0", "800x600x24", "-nolisten", "tcp"],  # noqa: S607
            pass_fds=(write,),
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
            preexec_fn=die_with_us,  # (no thread runs yet in `phalanx up`)
        )
        os.close(write)
        number = _read_line(read, XVFB_TIMEOUT_S)
        if not number.isdigit():
            self.close()
            raise ConfigError(f"Xvfb did not start a display within {XVFB_TIMEOUT_S:g} s")
        self.display = f":{number}"
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    def close(self) -> None:
        """Stop the X server; safe twice."""
        if self.process is not None and self.process.poll() is None:
            self.process.terminate()
            try:
                self.process.wait(5.0)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait(5.0)
        self.process = None


def _read_line(fd: int, timeout_s: float) -> str:
    """A line from pipe `fd` within `timeout_s` ("" if none came); closes `fd`."""
    import select

    data = b""
    with os.fdopen(fd, "rb", buffering=0) as pipe:
        while b"\n" not in data:
            ready, _, _ = select.select([pipe], [], [], timeout_s)
            chunk = pipe.read(64) if ready else b""
            if not chunk:
                break
            data += chunk
    return data.decode(errors="replace").strip()
