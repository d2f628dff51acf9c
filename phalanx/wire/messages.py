"""Versioned wire messages, one model per Zenoh key (see `phalanx.transport` for keys).

Encoding and decoding (and the drop-and-count of malformed payloads) live in
`phalanx.codec`; these are the values.
"""

from __future__ import annotations

import math
from operator import attrgetter
from typing import Final, Literal, Self

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)

from phalanx.core.config import MAX_ROBOTS
from phalanx.core.geometry import Pose2D, Twist2D
from phalanx.core.peers import FLAG_FIELDS, STATE_FIELDS, PeerFlags, PeerState, Scan
from phalanx.core.quantities import MAX_EXTENT_M, MAX_RANGE_M, Coordinate
from phalanx.wire.bounds import (
    MAX_BUMPERS,
    MAX_SONARS,
    MAX_STAMP_S,
    Count,
    Epoch,
    Heading,
    MaybeRobotId,
    Micros,
    Morph,
    Period,
    Range,
    RobotId,
    Seconds,
    Seq,
    ShapeIndex,
    Speed,
    Stamp,
    StateName,
    Text,
    Tick,
    UnixStamp,
    YawRate,
    fleet_bounds,
)

WIRE_VERSION: Final = 1


class Message(BaseModel):
    """Base of wire messages: frozen values, unknown fields and NaN/inf rejected.

    A non-finite number from a peer must never reach a controller: it would turn into a
    non-finite wheel command. Such a payload fails validation and is dropped and counted.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


class RobotState(Message):
    """What a robot publishes every control step on `.../robot/<id>/state`.

    Pose in the shared world frame (m, rad) at `stamp_s` on the fleet clock (sim time in
    lockstep, Unix time in real time); twist (m/s, rad/s) is the command the robot
    executes from `stamp_s` on, so a receiver can dead-reckon the pose to its own time.
    `leader_id` is the robot this one tracks ("" while it leads the formation); the
    rest are its behaviour flags (see `RobotFlags`), the state carries them too so a
    robot that tracks this one needs only this message. `cov`: the pose's covariance
    when the robot runs its pose estimator (upper triangle xx, xy, xt, yy, yt, tt in
    m^2, m rad, rad^2; see `check_pose_cov`), empty when it steers from its odometry as
    given.

    Its fields are `PeerState`'s (the record's one definition), in its order, each
    with its bound (tests/unit/test_robot_record.py holds them to it).
    """

    version: Literal[1] = 1
    robot_id: RobotId
    seq: Seq
    stamp_s: Stamp
    x_m: Coordinate
    y_m: Coordinate
    theta_rad: Heading
    v_mps: Speed
    omega_radps: YawRate
    fsm_state: StateName
    obstacle: bool = False
    direction: Literal[-1, 1] = 1  # in an EMERGENCY_STOP: the way it was going
    leader_id: MaybeRobotId = ""
    epoch: Epoch = 0
    formation_leader_id: MaybeRobotId = ""
    clear: bool = False
    formed: bool = True
    blocked_s: Seconds = 0.0
    dead_end: bool = False
    waypoint: Count = 0
    deadlocks: Count = 0
    profile_s: Seconds = 0.0
    cov: tuple[float, ...] = Field(default=(), max_length=6)
    shape_source: ShapeIndex = 0
    shape_target: ShapeIndex = 0
    morph: Morph = 1.0
    settled: bool = False
    shape_fits: bool = True

    @field_validator("cov")
    @classmethod
    def _cov_is_a_pose_covariance(cls, cov: tuple[float, ...]) -> tuple[float, ...]:
        return check_pose_cov(cov)

    @model_validator(mode="after")
    def _tracks_another(self) -> Self:
        if self.leader_id == self.robot_id:  # a leader tracks nobody: ""
            raise ValueError(f"{self.robot_id} cannot track itself")
        return self

    @property
    def pose(self) -> Pose2D:
        """The robot's pose."""
        return Pose2D(self.x_m, self.y_m, self.theta_rad)

    @property
    def twist(self) -> Twist2D:
        """The robot's twist."""
        return Twist2D(self.v_mps, self.omega_radps)

    def flags(self) -> RobotFlags:
        """The behaviour flags in this state (what every other robot needs)."""
        # Every value was validated when this state was built: no need to again.
        return RobotFlags.model_construct(**{name: getattr(self, name) for name in _FLAG_FIELDS})

    @classmethod
    def of(cls, state: PeerState) -> RobotState:
        """The wire message of an agent's state (validated)."""
        return cls.model_validate(dict(zip(STATE_FIELDS, _state_values(state), strict=True)))

    def peer(self) -> PeerState:
        """The state as the agent brain reads it."""
        return PeerState(*_state_values(self))


class RobotFlags(Message):
    """A robot's small behaviour flags on `.../robot/<id>/flags`, to every robot of the
    fleet, when they change and otherwise as a heartbeat (`agents.runtime.FlagsThrottle`):
    enough to take the leadership and deadlock decisions the same way on every robot
    (`phalanx.agents.leadership`), without anyone's pose.

    `obstacle`: its path is blocked (in its direction of motion), for `blocked_s`;
    `dead_end`: (a leader) its route leads back the way it came and the shape has no room
    to turn, so only the group's reverse helps, not a new leader;
    `clear`: its path ahead is free far enough to lead; `formed`: it is in its slot (a
    robot that is not may not be tracked); `formation_leader_id`/`epoch`: who it thinks
    leads, and under which epoch; `waypoint`, `deadlocks`, `profile_s`: the group's
    progress (next waypoint, deadlocks at it, scripted profile clock in s);
    `shape_source`, `shape_target`, `morph`: the shape the group is in or moving between
    (0 the scenario's, 1 shrunk, 2 column; `morph` of the way, 1 = there); `settled`:
    (a follower) on its slot at its heading, its leader standing still.

    Its fields are `PeerFlags`', in its order, each with its bound.
    """

    version: Literal[1] = 1
    robot_id: RobotId
    seq: Seq
    stamp_s: Stamp
    fsm_state: StateName
    obstacle: bool = False
    direction: Literal[-1, 1] = 1  # in an EMERGENCY_STOP: the way it was going
    epoch: Epoch = 0
    formation_leader_id: MaybeRobotId = ""
    clear: bool = False
    formed: bool = True
    blocked_s: Seconds = 0.0
    dead_end: bool = False
    waypoint: Count = 0
    deadlocks: Count = 0
    profile_s: Seconds = 0.0
    shape_source: ShapeIndex = 0
    shape_target: ShapeIndex = 0
    morph: Morph = 1.0
    settled: bool = False

    @classmethod
    def of(cls, flags: PeerFlags) -> RobotFlags:
        """The wire message of an agent's flags (validated)."""
        return cls.model_validate(dict(zip(FLAG_FIELDS, _flag_values(flags), strict=True)))

    def peer(self) -> PeerFlags:
        """The flags as the agent brain reads them."""
        return PeerFlags(*_flag_values(self))


_FLAG_FIELDS = tuple(RobotFlags.model_fields)
# A record's values in its order (the same names on the brain's value and on the wire's).
_state_values: Final = attrgetter(*STATE_FIELDS)
_flag_values: Final = attrgetter(*FLAG_FIELDS)
FIX_FIELDS = ("stamp_s", "x_m", "y_m", "theta_rad", "std_m", "std_rad")
RELATIVE_FIELDS = (
    "stamp_s", "target", "range_m", "bearing_rad", "heading_rad", "std_range_m",
    "std_bearing_rad", "std_heading_rad",
)  # fmt: skip
MAX_MEASUREMENTS = 1000  # per frame: 10 s of 100 Hz motion capture
_TWO_PI = 2.0 * math.pi
# Each field's (low, high) in a sense frame's flattened groups: stamps within the run,
# poses within the world, standard deviations bounded as the messages' (the simulated
# sensors' are never 0; an in-process run does not check them, so neither does a frame).
FIX_LIMITS: Final = (
    (0.0, MAX_STAMP_S), (-MAX_EXTENT_M, MAX_EXTENT_M), (-MAX_EXTENT_M, MAX_EXTENT_M),
    (-_TWO_PI, _TWO_PI), (0.0, 10.0), (0.0, math.pi),
)  # fmt: skip
RELATIVE_LIMITS: Final = (
    (0.0, MAX_STAMP_S), (0.0, 1000.0), (0.0, MAX_RANGE_M), (-_TWO_PI, _TWO_PI),
    (-_TWO_PI, _TWO_PI), (0.0, 10.0), (0.0, math.pi), (0.0, math.pi),
)  # fmt: skip
_MAX_FIX_VALUES: Final = len(FIX_FIELDS) * MAX_MEASUREMENTS
_MAX_RELATIVE_VALUES: Final = len(RELATIVE_FIELDS) * MAX_MEASUREMENTS
# A pose variance beyond these means the robot has no idea where it is: (1 km)^2 and
# (pi rad)^2; larger ones are not physics but a broken sender.
MAX_POSITION_VAR_M2 = 1e6
MAX_HEADING_VAR_RAD2 = math.pi**2
_COV_TOLERANCE = 1e-9


class LeaderAnnouncement(Message):
    """A leadership change on `phalanx/<fleet>/leader`: who leads from `stamp_s` on,
    under which `epoch`, and why. Sent by the new leader; every robot reaches the same
    decision from the flags on its own, so this is the fleet's record of it (and what a
    tool watches), not a command.
    """

    version: Literal[1] = 1
    leader_id: RobotId
    epoch: Epoch
    stamp_s: Stamp
    previous_id: MaybeRobotId = ""
    reason: Text = ""


class ClockTick(Message):
    """A lockstep tick from the world on `phalanx/<fleet>/clock`."""

    version: Literal[1] = 1
    tick: Tick
    t_s: Stamp
    dt_s: Period
    final: bool = False


class VelocityCommand(Message):
    """An agent's command for a simulated robot on `.../robot/<id>/cmd`."""

    version: Literal[1] = 1
    robot_id: RobotId
    tick: Tick
    stamp_s: Stamp
    v_mps: Speed
    omega_radps: YawRate


class OperatorCommand(Message):
    """What an operator asks of robot `robot_id`, the robot that leads, on
    `.../robot/<id>/operator` (`phalanx ros2` passes ROS 2's `cmd_vel` and `goal_pose`
    on): a twist to drive by (`twist`: `v_mps`, `omega_radps`, before the robot's limits),
    a goal to go to (`goal`: `goal_x_m`, `goal_y_m` in the fleet's world frame), or both.

    `stamp_s`: when the operator sent it (Unix time); a receiver takes none stamped no
    later than the last it took, and a twist drives the robot for a short while from
    when the robot heard it (`phalanx.agents.inputs.OPERATOR_TIMEOUT_S`). Speeds are
    held to the robots' rating, like a state's.
    """

    version: Literal[1] = 1
    robot_id: RobotId
    stamp_s: UnixStamp
    twist: bool = False
    v_mps: Speed = 0.0
    omega_radps: YawRate = 0.0
    goal: bool = False
    goal_x_m: Coordinate = 0.0
    goal_y_m: Coordinate = 0.0

    @model_validator(mode="after")
    def _asks_something(self) -> Self:
        if not (self.twist or self.goal):
            raise ValueError("an operator command asks for a twist, a goal, or both")
        return self


class SenseFrame(Message):
    """What the world tells a simulated robot each tick on `.../robot/<id>/sense`.

    In lockstep it is also the robot's tick: the agent answers with a VelocityCommand
    for the same `tick`. Odometry pose (m, rad) in the world frame, measured twist.
    """

    version: Literal[1] = 1
    robot_id: RobotId
    tick: Tick
    t_s: Stamp
    dt_s: Period
    x_m: Coordinate
    y_m: Coordinate
    theta_rad: Heading
    v_mps: Speed
    omega_radps: YawRate
    sonar_ranges_m: tuple[Range, ...] = Field(default=(), max_length=MAX_SONARS)
    bumpers: tuple[bool, ...] = Field(default=(), max_length=MAX_BUMPERS)
    final: bool = False
    # Positioning measurements that reached the robot since its last frame (simulated
    # sensors, `phalanx.simulator.sensors`), flattened: `fixes` in groups of
    # FIX_FIELDS, `relative` in groups of RELATIVE_FIELDS (target: its index in the
    # scenario's robot list; heading 0 with std 0: not measured). Stamps in sim time.
    fixes: tuple[float, ...] = Field(default=(), max_length=_MAX_FIX_VALUES)
    relative: tuple[float, ...] = Field(default=(), max_length=_MAX_RELATIVE_VALUES)
    # Lockstep: the other robots' newest states the world heard (one message in a tick).
    peers: tuple[RobotState, ...] = Field(default=(), max_length=MAX_ROBOTS)

    @field_validator("fixes")
    @classmethod
    def _whole_fixes(cls, values: tuple[float, ...]) -> tuple[float, ...]:
        return _groups_of(values, FIX_LIMITS, "fixes")

    @field_validator("relative")
    @classmethod
    def _whole_relatives(cls, values: tuple[float, ...]) -> tuple[float, ...]:
        return _groups_of(values, RELATIVE_LIMITS, "relative")

    @model_validator(mode="after")
    def _on_the_clock(self, info: ValidationInfo) -> Self:
        # A frame is tick k at k * dt: a frame whose time is not its tick's is not the
        # world's (the run's clock would jump to wherever it says).
        if abs(self.t_s - self.tick * self.dt_s) > 1e-6 * max(1.0, self.t_s):
            raise ValueError(f"t_s {self.t_s} is not tick {self.tick} x dt_s {self.dt_s}")
        bounds = fleet_bounds(info)
        if bounds is not None and abs(self.dt_s - bounds.dt_s) > 1e-9:
            raise ValueError(f"dt_s {self.dt_s} is not the run's {bounds.dt_s}")
        ids = [p.robot_id for p in self.peers]  # (a state of this tick is none heard yet)
        late = any(p.stamp_s > self.t_s - 0.5 * self.dt_s for p in self.peers)
        if late or self.robot_id in ids or len(set(ids)) != len(ids):
            raise ValueError("peers must be other robots' states (one each) of earlier ticks")
        return self


class ScanMessage(Message):
    """One sonar reading of robot `robot_id` for the fleet's shared map, on
    `.../robot/<id>/scan`: where it was taken (world frame, m and rad, at `stamp_s` on the
    fleet clock), one range per transducer (m) and which are echoes of obstacles (the
    formation's own robots masked out by the sender).
    """

    version: Literal[1] = 1
    robot_id: RobotId
    stamp_s: Stamp
    x_m: Coordinate
    y_m: Coordinate
    theta_rad: Heading
    ranges_m: tuple[Range, ...] = Field(max_length=MAX_SONARS)
    echo: tuple[bool, ...] = Field(max_length=MAX_SONARS)

    @model_validator(mode="after")
    def _an_echo_flag_per_range(self, info: ValidationInfo) -> Self:
        if len(self.echo) != len(self.ranges_m):
            raise ValueError(f"{len(self.echo)} echo flags for {len(self.ranges_m)} ranges")
        bounds = fleet_bounds(info)
        if bounds is not None and bounds.sonars and len(self.ranges_m) not in (0, bounds.sonars):
            raise ValueError(
                f"{len(self.ranges_m)} ranges from a fleet whose robots have {bounds.sonars} sonars"
            )
        return self

    @classmethod
    def of(cls, scan: Scan) -> ScanMessage:
        """The wire message of a robot's scan (validated)."""
        return cls(
            robot_id=scan.robot_id, stamp_s=scan.stamp_s, x_m=scan.x_m, y_m=scan.y_m,
            theta_rad=scan.theta_rad, ranges_m=scan.ranges_m, echo=scan.echo,
        )  # fmt: skip

    def scan(self) -> Scan:
        """The scan as the agent brain reads it."""
        return Scan(
            self.robot_id, self.stamp_s, self.x_m, self.y_m, self.theta_rad, self.ranges_m,
            self.echo,
        )  # fmt: skip


class AgentEvent(Message):
    """A behaviour-state transition, on `.../robot/<id>/event`."""

    version: Literal[1] = 1
    robot_id: RobotId
    t_s: Stamp
    source: StateName
    target: StateName
    reason: Text


class AgentReport(Message):
    """An agent's counters when a run ends, on `.../robot/<id>/report`."""

    version: Literal[1] = 1
    robot_id: RobotId
    steps: Count
    saturations: Count
    accel_limited: Count
    dropped_messages: Count
    late_peer_steps: Count
    step_p50_us: Micros = 0.0  # control step: core, publish, telemetry
    step_p99_us: Micros = 0.0
    telemetry_dropped: Count = 0
    commands_sent: Count = 0  # a robot on a driver: commands its driver took


def check_pose_cov(cov: tuple[float, ...]) -> tuple[float, ...]:
    """A pose covariance as the wire carries it, checked: empty, or the six values of the
    upper triangle (xx, xy, xt, yy, yt, tt), variances within physics
    (`MAX_POSITION_VAR_M2`, `MAX_HEADING_VAR_RAD2`) and each covariance no larger than
    its variances allow (|c_ij| <= sqrt(c_ii c_jj)).
    """
    if not cov:
        return cov
    if len(cov) != 6:
        raise ValueError(f"cov: expected 0 or 6 values (xx, xy, xt, yy, yt, tt), got {len(cov)}")
    xx, xy, xt, yy, yt, tt = cov
    for name, var, bound in (("xx", xx, MAX_POSITION_VAR_M2), ("yy", yy, MAX_POSITION_VAR_M2),
                             ("tt", tt, MAX_HEADING_VAR_RAD2)):  # fmt: skip
        if not 0.0 <= var <= bound:
            raise ValueError(f"cov: variance {name} must be within [0, {bound:g}], got {var!r}")
    for name, c, a, b in (("xy", xy, xx, yy), ("xt", xt, xx, tt), ("yt", yt, yy, tt)):
        if abs(c) > math.sqrt(a * b) * (1.0 + _COV_TOLERANCE) + _COV_TOLERANCE:
            raise ValueError(f"cov: |{name}| = {abs(c)!r} exceeds what its variances allow")
    return cov


def _groups_of(
    values: tuple[float, ...], limits: tuple[tuple[float, float], ...], name: str
) -> tuple[float, ...]:
    """Whole groups of `len(limits)` values, each within its field's (low, high)."""
    size = len(limits)
    if len(values) % size or len(values) > size * MAX_MEASUREMENTS:
        raise ValueError(
            f"{name}: expected whole groups of {size} values, at most {MAX_MEASUREMENTS}, "
            f"got {len(values)} values"
        )
    for i, value in enumerate(values):
        low, high = limits[i % size]
        if not low <= value <= high:
            raise ValueError(f"{name}[{i}] = {value!r} is outside [{low:g}, {high:g}]")
    return values
