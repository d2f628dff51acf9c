"""What a robot shares with its fleet every control step, as plain values.

The agent brain produces a `PeerState` each step and reads its peers' states and flags
in the same form; the wire (`phalanx.wire.messages`) validates and encodes them at the
edge of a process. In one process (the batch runner) they pass from robot to robot as
they are, with no validation on the hot path.

`PeerState` is the one definition of the record: its fields' names, order, types and
defaults. `PeerFlags` is the subset of them every robot needs (its fields, in the same
order); `PeerState.flags()`, the wire messages' conversions and the packed layout
(`phalanx.wire.codec`, an int in the width its annotation gives: `Int8`, `UInt32`) are
derived from the two, and tests/unit/test_robot_record.py fails if the wire models, which
declare each field's bounds, drift from them.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from operator import attrgetter
from typing import Annotated, Final

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


@dataclass(frozen=True, slots=True)
class IntWidth:
    """The width an integer field of a shared record travels in: `bits`, signed or not."""

    bits: int
    signed: bool

    @property
    def low(self) -> int:
        """The smallest value it holds."""
        return -(1 << (self.bits - 1)) if self.signed else 0

    @property
    def high(self) -> int:
        """The largest value it holds."""
        return (1 << (self.bits - 1 if self.signed else self.bits)) - 1


# An int field of a record takes one of these (the packed layout needs its width).
Int8 = Annotated[int, IntWidth(8, signed=True)]
UInt32 = Annotated[int, IntWidth(32, signed=False)]


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
    1 shrunk, 2 column; `morph` of the way from the first to the second, 1 = there);
    `settled`: (a follower) it stands on its slot at the slot's heading, its leader
    standing still (a leader pausing before a deadlock reverse may back off).

    Its fields are fields of `PeerState`, declared as there, in the same order.
    """

    robot_id: str
    seq: UInt32
    stamp_s: float
    fsm_state: str
    obstacle: bool = False
    direction: Int8 = 1
    epoch: UInt32 = 0
    formation_leader_id: str = ""
    clear: bool = False
    formed: bool = True
    blocked_s: float = 0.0
    dead_end: bool = False
    waypoint: UInt32 = 0
    deadlocks: UInt32 = 0
    profile_s: float = 0.0
    shape_source: Int8 = 0
    shape_target: Int8 = 0
    morph: float = 1.0
    settled: bool = False


@quick_init
@dataclass(frozen=True, slots=True)
class PeerState:
    """A robot's state: pose in the shared world frame (m, rad) at `stamp_s` on the fleet
    clock; twist (m/s, rad/s) it executes from `stamp_s` on, so a receiver can
    dead-reckon the pose to its own time; `leader_id`, the robot it tracks ("" while it
    leads); and its flags (see `PeerFlags`), so a robot tracking it needs nothing else.

    `shape_fits`: (a navigating leader) whether its map shows the scenario's shape
    fitting the way (`phalanx.agents.reshape.ShapeKeeper.scenario_fits`); True for any
    other robot. Nobody steers by it: it goes on the record of the run.

    `cov`: the covariance of the pose, when the robot estimates it (its pose estimator
    is on), as the upper triangle `(xx, xy, xt, yy, yt, tt)` in m^2, m rad and rad^2
    (`phalanx.core.fixes`); empty when the robot steers from its odometry as given
    (perfect sensing), which a receiver takes as exact.

    The one definition of the record (see the module's docstring): a field added here
    (and to `PeerFlags`, if every robot needs it) is declared on the wire messages with
    its bound; the conversions and the packed layout follow.
    """

    robot_id: str
    seq: UInt32
    stamp_s: float
    x_m: float
    y_m: float
    theta_rad: float
    v_mps: float
    omega_radps: float
    fsm_state: str
    obstacle: bool = False
    direction: Int8 = 1
    leader_id: str = ""
    epoch: UInt32 = 0
    formation_leader_id: str = ""
    clear: bool = False
    formed: bool = True
    blocked_s: float = 0.0
    dead_end: bool = False
    waypoint: UInt32 = 0
    deadlocks: UInt32 = 0
    profile_s: float = 0.0
    cov: tuple[float, ...] = ()
    shape_source: Int8 = 0
    shape_target: Int8 = 0
    morph: float = 1.0
    settled: bool = False
    shape_fits: bool = True

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
        return PeerFlags(*_flag_values(self))


# The record's field names in order, and its flags' (a subset of them, in the same order).
STATE_FIELDS: Final = tuple(f.name for f in dataclasses.fields(PeerState))
FLAG_FIELDS: Final = tuple(f.name for f in dataclasses.fields(PeerFlags))
_flag_values: Final = attrgetter(*FLAG_FIELDS)


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
