"""ARIA clients (code nobody here wrote) against `phalanx emulate p3dx --tcp`: they
connect without a warning, read the CONFIG packet as a P3DX's, and their motion commands
(setVel2 with negative wheels, setHeading, setDeltaHeading, move) end where they should;
AriaCoda's simpleMotionCommands ends where it ends on AMRISim. Skipped unless
PHALANX_ARIA_EXAMPLES (and, for the comparison, PHALANX_AMRISIM) are given
(docs/INTEROP.md)."""

from __future__ import annotations

import math
import re
import statistics
import sys
from typing import Any

import pytest

pytestmark = [pytest.mark.drivers, pytest.mark.integration]


def report(text: str) -> None:
    """Figures for docs/INTEROP.md (shown with `pytest -s`)."""
    sys.stdout.write(f"{text}\n")


Fixture = Any  # conftest.py's objects: Aria, Emulator, Amrisim, record and replay
# ARIA's complaints about a robot: the limits it refuses from a bad CONFIG packet
# ("ArRobot::setAbsoluteMaxTransAccel: given a value <= 0 (0) and will not set it",
# "ArRobot: setTransVelMax of 0 is below 0, ignoring it": ten of them before the CONFIG
# fix), capped ones, missing packets, failed steps. The example's own banner ("WARNING:
# this program does no sensing ...") is not one.
COMPLAINT = re.compile(
    r"ignoring|will not|capping|below 0|over the absolute|[Ww]arning|Could not|[Ff]ailed|[Ee]rror"
)
BANNER = "this program does no sensing"


def _complaints(output: str) -> list[str]:
    return [line for line in output.splitlines() if COMPLAINT.search(line) and BANNER not in line]


def _steps(output: str) -> dict[str, dict[str, float]]:
    steps = {}
    for line in output.splitlines():
        if line.startswith("PHALANX step="):
            fields = dict(part.split("=", 1) for part in line.split()[1:])
            name = fields.pop("step")
            steps[name] = {k: float(v) for k, v in fields.items()}
    return steps


def _end_pose(output: str) -> tuple[float, float, float]:
    poses = re.findall(r"Pose=\((-?[\d.]+),(-?[\d.]+),(-?[\d.]+)\)", output)
    x, y, th = poses[-1]
    return float(x), float(y), float(th)


def test_aria_drives_the_emulator_as_a_p3dx(
    aria: Fixture, aria_motion_check: Fixture, emulator: Fixture
) -> None:
    output = aria.run(aria_motion_check, emulator.port)
    report(output)
    assert not _complaints(output)
    steps = _steps(output)
    assert steps["end"]["ok"] == 1
    config = steps["config"]
    assert (config["trans_vel_max"], config["rot_vel_max"], config["watchdog"]) == (1200, 300, 2000)
    assert (config["trans_accel"], config["trans_decel"], config["rot_accel"]) == (300, 300, 100)
    assert config["real_battery"] == pytest.approx(12.5)
    back = steps["vel2_back"]  # both wheels -200 mm/s for 2 s (+ ARIA's timing): backwards
    assert -430.0 < back["x"] < -370.0
    assert abs(back["y"]) < 2.0
    assert steps["vel2_turn"]["th"] > 45.0  # left -100, right +100: counter-clockwise
    # ARIA's AngleConvFactor (0.00153) reads a P3DX's heading 0.26 % short of the robot's.
    assert steps["heading_90"]["th"] == pytest.approx(90.0, abs=1.0)
    assert steps["delta_heading_-45"]["th"] == pytest.approx(45.0, abs=1.0)
    start, moved = steps["delta_heading_-45"], steps["move_1000"]
    dx, dy = moved["x"] - start["x"], moved["y"] - start["y"]
    assert math.hypot(dx, dy) == pytest.approx(1000.0, abs=10.0)
    assert math.degrees(math.atan2(dy, dx)) == pytest.approx(start["th"], abs=1.0)
    back_moved = steps["move_-500"]
    assert math.hypot(back_moved["x"] - moved["x"], back_moved["y"] - moved["y"]) == (
        pytest.approx(500.0, abs=10.0)
    )


def test_the_same_program_on_amrisim(
    aria: Fixture, aria_motion_check: Fixture, amrisim: Fixture
) -> None:
    """What AMRISim makes of our ARIA program, for docs/INTEROP.md (only its connecting and
    the CONFIG it sends are asserted: its MOVE and battery quirks are its own)."""
    output = aria.run(aria_motion_check, amrisim.port)
    report(output)
    steps = _steps(output)
    assert steps["end"]["ok"] == 1
    assert steps["config"]["trans_vel_max"] == 3000


@pytest.mark.timeout(600)
def test_simple_motion_commands_ends_where_it_ends_on_amrisim(
    aria: Fixture, emulator: Fixture, amrisim: Fixture, recorder: Fixture, replayer: Fixture
) -> None:
    """AriaCoda's examples/simpleMotionCommands, live on each, then the very command stream
    it sent (recorded through a proxy) replayed to both at its recorded times: a live run
    carries ARIA's and AMRISim's timing (commands go out on ARIA's 100 ms cycle; AMRISim
    applies them on its own update loop), the replay compares the two robots alone."""
    program = aria.examples / "simpleMotionCommands"
    live = recorder(aria, program, emulator.port)
    report(live.output)
    assert not _complaints(live.output)
    on_emulator = _end_pose(live.output)
    on_amrisim = _end_pose(aria.run(program, amrisim.port))
    replays = []
    for _ in range(3):
        amrisim.next_port()  # AMRISim listens on the next port after each client
        replays.append(replayer(live.frames, amrisim.port))
    emulated = replayer(live.frames, emulator.port)
    reference = tuple(statistics.median(r[i] for r in replays) for i in range(3))
    report(f"live end poses (mm, mm, deg): emulator {on_emulator}, AMRISim {on_amrisim}")
    report(f"replayed: emulator {emulated}; AMRISim {replays} (median {reference})")
    gaps = [
        (math.hypot(emulated[0] - r[0], emulated[1] - r[1]), abs(emulated[2] - r[2]))
        for r in [*replays, reference]
    ]
    report("replay gaps (mm, deg) to each AMRISim replay, then to their median: " + str(gaps))
    # AMRISim applies a command on its next 100 ms update, so the same stream ends up to
    # one update's motion apart from one replay to the next (1 deg at 10 deg/s): the
    # emulator must end where AMRISim ends on one of them.
    assert min((mm for mm, deg in gaps[:-1] if deg < 1.0), default=math.inf) < 20.0
