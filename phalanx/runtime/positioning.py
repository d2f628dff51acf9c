"""Positioning measurements between processes: pose fixes and relative measurements as
the wire carries them, and the inbox through which a robot on a driver hears them.

- A simulated robot gets its simulated sensors' measurements in its world sense frame
  (`SenseFrame.fixes` / `.relative`, flattened, stamps in sim time): one message a tick,
  so a lockstep run stays deterministic and equal to the in-process one.
- A robot on a driver hears fixes on `robot/<id>/fix` (from `phalanx mocap`, or from a
  world process that simulates motion capture for emulated robots) and, from a world
  process, its simulated camera on `robot/<id>/relative`; stamps there are Unix time, and
  the inbox turns them into fleet time with the run's epoch.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Sequence
from pathlib import Path

from phalanx.core.config import Scenario
from phalanx.core.config_files import validate_file
from phalanx.core.errors import ConfigError
from phalanx.core.fixes import PoseFix, RelativeFix
from phalanx.core.localisation import CameraCalibration, MarkerSource
from phalanx.drivers.markers import MarkerCamera, MarkerDetector
from phalanx.wire.keys import robot_key
from phalanx.wire.messages import FIX_FIELDS, RELATIVE_FIELDS, SenseFrame
from phalanx.wire.positions import PoseFixMessage, RelativeFixMessage
from phalanx.wire.transport import FleetSession

log = logging.getLogger("phalanx.positioning")
# An inbox keeps at most this many measurements between two steps (the oldest go first).
MAX_PENDING = 2000


def flatten_fixes(fixes: Sequence[PoseFix]) -> tuple[float, ...]:
    """Fixes as `SenseFrame.fixes` carries them."""
    return tuple(
        v for f in fixes for v in (f.stamp_s, f.x_m, f.y_m, f.theta_rad, f.std_m, f.std_rad)
    )


def flatten_relative(relative: Sequence[RelativeFix], ids: Sequence[str]) -> tuple[float, ...]:
    """Relative measurements as `SenseFrame.relative` carries them (targets by index)."""
    out: list[float] = []
    for r in relative:
        heading, std_h = (0.0, 0.0) if r.heading_rad is None else (r.heading_rad, r.std_heading_rad)
        out += (r.stamp_s, float(ids.index(r.target_id)), r.range_m, r.bearing_rad, heading,
                r.std_range_m, r.std_bearing_rad, std_h)  # fmt: skip
    return tuple(out)


def frame_fixes(frame: SenseFrame) -> tuple[PoseFix, ...]:
    """The pose fixes a sense frame carries."""
    n = len(FIX_FIELDS)
    values = frame.fixes
    return tuple(PoseFix(*values[i : i + n]) for i in range(0, len(values), n))


def frame_relative(frame: SenseFrame, ids: Sequence[str]) -> tuple[RelativeFix, ...]:
    """The relative measurements a sense frame carries (unknown targets left out)."""
    n, values, out = len(RELATIVE_FIELDS), frame.relative, []
    for i in range(0, len(values), n):
        stamp, target, rng, bearing, heading, s_r, s_b, s_h = values[i : i + n]
        index = int(target)
        if index != target or not 0 <= index < len(ids):
            continue
        heading_or_none = heading if s_h > 0.0 else None
        out.append(RelativeFix(stamp, ids[index], rng, bearing, s_r, s_b, heading_or_none, s_h))
    return tuple(out)


def fix_message(robot_id: str, fix: PoseFix, *, epoch_s: float) -> PoseFixMessage:
    """A fix (stamped in fleet time) as the wire carries it (Unix time)."""
    return PoseFixMessage(
        robot_id=robot_id,
        stamp_s=epoch_s + fix.stamp_s,
        x_m=fix.x_m,
        y_m=fix.y_m,
        theta_rad=fix.theta_rad,
        std_m=fix.std_m,
        std_rad=fix.std_rad,
    )


def relative_message(robot_id: str, rel: RelativeFix, *, epoch_s: float) -> RelativeFixMessage:
    """A relative measurement (stamped in fleet time) as the wire carries it."""
    return RelativeFixMessage(
        robot_id=robot_id,
        target_id=rel.target_id,
        stamp_s=epoch_s + rel.stamp_s,
        range_m=rel.range_m,
        bearing_rad=rel.bearing_rad,
        heading_rad=rel.heading_rad or 0.0,
        std_range_m=rel.std_range_m,
        std_bearing_rad=rel.std_bearing_rad,
        std_heading_rad=rel.std_heading_rad if rel.heading_rad is not None else 0.0,
    )


class PositioningInbox:
    """What a robot on a driver hears of its positioning sources, between two steps."""

    def __init__(self, fleet: str, robot_id: str, *, epoch_s: float) -> None:
        self.fleet, self.robot_id, self.epoch_s = fleet, robot_id, epoch_s
        self._lock = threading.Lock()
        self._fixes: list[PoseFix] = []
        self._relative: list[RelativeFix] = []
        self.received = 0
        self.refused = 0  # for another robot, or overflowing
        self.camera: MarkerCamera | None = None  # this robot's own, read on this computer

    def attach(self, session: FleetSession) -> None:
        """Listen on this robot's `fix` and `relative` keys."""
        key = robot_key(self.fleet, self.robot_id, "fix")
        session.subscribe(key, PoseFixMessage, lambda _k, m: self._on_fix(m))
        key = robot_key(self.fleet, self.robot_id, "relative")
        session.subscribe(key, RelativeFixMessage, lambda _k, m: self._on_relative(m))

    def _on_fix(self, message: PoseFixMessage) -> None:
        if message.robot_id != self.robot_id:
            self.refused += 1
            return
        fix = PoseFix(
            message.stamp_s - self.epoch_s, message.x_m, message.y_m, message.theta_rad,
            message.std_m, message.std_rad,
        )  # fmt: skip
        self._keep(self._fixes, fix)

    def _on_relative(self, message: RelativeFixMessage) -> None:
        if message.robot_id != self.robot_id or message.target_id == self.robot_id:
            self.refused += 1
            return
        has_heading = message.std_heading_rad > 0.0
        rel = RelativeFix(
            message.stamp_s - self.epoch_s, message.target_id, message.range_m,
            message.bearing_rad, message.std_range_m, message.std_bearing_rad,
            message.heading_rad if has_heading else None, message.std_heading_rad,
        )  # fmt: skip
        self._keep(self._relative, rel)

    def _keep(self, into: list[PoseFix] | list[RelativeFix], item: PoseFix | RelativeFix) -> None:
        if not math.isfinite(item.stamp_s):
            self.refused += 1
            return
        with self._lock:
            self.received += 1
            into.append(item)  # type: ignore[arg-type]
            if len(into) > MAX_PENDING:
                del into[0]
                self.refused += 1

    def drain(self) -> tuple[tuple[PoseFix, ...], tuple[RelativeFix, ...]]:
        """Everything heard since the last call."""
        with self._lock:
            fixes, relative = tuple(self._fixes), tuple(self._relative)
            self._fixes.clear()
            self._relative.clear()
        if self.camera is not None:
            relative += self.camera.drain()
        return fixes, relative

    def close(self) -> None:
        """Stop the camera, if any (safe twice)."""
        if self.camera is not None:
            self.camera.close()


def open_camera(spec: str, robot_id: str, scenario: Scenario, *, epoch_s: float) -> MarkerCamera:
    """The robot's marker camera from `DEVICE=CALIBRATION.toml`, started, its frames
    stamped in fleet time (Unix time less `epoch_s`, less the markers' `latency_s`).
    """
    device, sep, calibration_path = spec.partition("=")
    if not sep:
        raise ConfigError(f"--camera {spec!r}: expected DEVICE=CALIBRATION.toml")
    calibration = validate_file(CameraCalibration, Path(calibration_path))
    source = scenario.localisation.markers or MarkerSource()
    ids = tuple(r.id for r in scenario.robots)
    detector = MarkerDetector(calibration, source, robot_ids=ids, own_id=robot_id)
    camera = MarkerCamera(
        device, detector, clock=lambda: time.time() - epoch_s, latency_s=source.latency_s
    )
    return camera.start()
