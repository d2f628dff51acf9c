"""What a robot shares with its fleet every control step, as plain values.

The agent brain produces a `PeerState` each step and reads its peers' states and flags
in the same form; the wire (`phalanx.wire.messages`) validates and encodes them at the
edge of a process. In one process (the batch runner) they pass from robot to robot as
they are, with no validation on the hot path.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

from phalanx.core.frozen import quick_init
from phalanx.core.geometry import Pose2D, Twist2D

# Epochs and sequence numbers travel as unsigned 32-bit integers. An epoch grows by one
# per leadership change; at the top it stays (`next_epoch`): leadership then passes at
# the same epoch, by the formation's order, rather than by wrapping round to 0, which
# every robot would take for an old claim.
EPOCH_MAX: Final = 2**32 - 1
SEQ_MAX: Final = 2**32 - 1


def next_epoch(epoch: int) -> int:
    """The epoch a new leadership claim takes after `epoch` (saturating at EPOCH_MAX)."""
    return min(epoch + 1, EPOCH_MAX)


@quick_init
@dataclass(frozen=True, slots=True)
class PeerFlags:
    """A robot's behaviour flags: enough for every robot to take the leadership and
    deadlock decisions the same way (`phalanx.agents.leadership`), without its pose.

    `obstacle`: its path is blocked (in its `direction` of motion, +1 or -1), for
    `blocked_s`; in an emergency stop, `direction` is the way it was going when it
    stopped (the side what stopped it is on), `obstacle` still the way ahead;
    `dead_end`: (a leader) its route leads back the way it came and the shape has no
    room to turn; `clear`: its path ahead is free far enough to lead;
    `formed`: it is in its slot (a robot that is not may not be tracked);
    `formation_leader_id`/`epoch`: who it thinks leads, under which epoch; `waypoint`,
    `deadlocks`, `profile_s`: the group's progress (next waypoint, deadlocks at it,
    scripted profile clock in s); `shape_source`, `shape_target`, `morph`: the shape the
    group is in, or moving between (`phalanx.core.shapes.ShapeKey`: 0 the scenario's,
    1 shrunk, 2 column; `morph` of the way from the first to the second, 1 = there).
    """

    robot_id: str
    seq: int
    stamp_s: float
    fsm_state: str
    obstacle: bool = False
    direction: int = 1
    epoch: int = 0
    formation_leader_id: str = ""
    clear: bool = False
    formed: bool = True
    blocked_s: float = 0.0
    dead_end: bool = False
    waypoint: int = 0
    deadlocks: int = 0
    profile_s: float = 0.0
    shape_source: int = 0
    shape_target: int = 0
    morph: float = 1.0


@quick_init
@dataclass(frozen=True, slots=True)
class PeerState:
    """A robot's state: pose in the shared world frame (m, rad) at `stamp_s` on the fleet
    clock; twist (m/s, rad/s) it executes from `stamp_s` on, so a receiver can
    dead-reckon the pose to its own time; `leader_id`, the robot it tracks ("" while it
    leads); and its flags (see `PeerFlags`), so a robot tracking it needs nothing else.

    `cov`: the covariance of the pose, when the robot estimates it (its pose estimator
    is on), as the upper triangle `(xx, xy, xt, yy, yt, tt)` in m^2, m rad and rad^2
    (`phalanx.core.fixes`); empty when the robot steers from its odometry as given
    (perfect sensing), which a receiver takes as exact.
    """

    robot_id: str
    seq: int
    stamp_s: float
    x_m: float
    y_m: float
    theta_rad: float
    v_mps: float
    omega_radps: float
    fsm_state: str
    obstacle: bool = False
    direction: int = 1
    leader_id: str = ""
    epoch: int = 0
    formation_leader_id: str = ""
    clear: bool = False
    formed: bool = True
    blocked_s: float = 0.0
    dead_end: bool = False
    waypoint: int = 0
    deadlocks: int = 0
    profile_s: float = 0.0
    cov: tuple[float, ...] = ()
    shape_source: int = 0
    shape_target: int = 0
    morph: float = 1.0

    @property
    def pose(self) -> Pose2D:
        """The robot's pose."""
        return Pose2D(self.x_m, self.y_m, self.theta_rad)

    @property
    def twist(self) -> Twist2D:
        """The robot's twist."""
        return Twist2D(self.v_mps, self.omega_radps)

    def flags(self) -> PeerFlags:
        """The behaviour flags in this state (what every other robot needs)."""
        return PeerFlags(
            robot_id=self.robot_id,
            seq=self.seq,
            stamp_s=self.stamp_s,
            fsm_state=self.fsm_state,
            obstacle=self.obstacle,
            direction=self.direction,
            epoch=self.epoch,
            formation_leader_id=self.formation_leader_id,
            clear=self.clear,
            formed=self.formed,
            blocked_s=self.blocked_s,
            dead_end=self.dead_end,
            waypoint=self.waypoint,
            deadlocks=self.deadlocks,
            profile_s=self.profile_s,
            shape_source=self.shape_source,
            shape_target=self.shape_target,
            morph=self.morph,
        )


@dataclass(frozen=True, slots=True)
class Scan:
    """One sonar reading a robot adds to the fleet's shared map: where it was taken
    (pose in the world frame, m and rad, at `stamp_s` on the fleet clock), the ranges
    (m, one per transducer) and which of them are echoes of obstacles (`echo`: the
    formation's own robots already masked out).
    """

    robot_id: str
    stamp_s: float
    x_m: float
    y_m: float
    theta_rad: float
    ranges_m: tuple[float, ...]
    echo: tuple[bool, ...]

    @property
    def pose(self) -> Pose2D:
        """Where the reading was taken."""
        return Pose2D(self.x_m, self.y_m, self.theta_rad)
