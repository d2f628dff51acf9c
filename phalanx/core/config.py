"""Configuration models (pydantic v2) for scenarios (robots' own: `robot_params`).

Every model forbids unknown keys and is frozen. `phalanx.core.config_files` reads them
from TOML files, with errors naming the file, the field path and a misspelt key's fix.
"""

from __future__ import annotations

import math
import re
from pathlib import PurePath
from typing import Annotated, Literal, Self

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, model_validator

from phalanx.core.geometry import Pose2D
from phalanx.core.localisation import LocalisationConfig
from phalanx.core.quantities import (
    MAX_DURATION_S,
    MAX_YAW_RATE_RADPS,
    Angle,
    Coordinate,
    Duration,
    Fraction,
    Gain,
    Length,
    NonNegativeSpeed,
    PositiveDuration,
    PositiveLength,
    PositiveRange,
    PositiveSpeed,
    PositiveYawRate,
    SensorRange,
    SignedSpeed,
    SignedYawRate,
)

# Resources a scenario may ask for (a run keeps every robot's trace in memory, about 100
# bytes per robot and step): a mistyped file must not eat the machine before it starts.
MAX_ROBOTS = 1000  # the largest fleet the batch runner is measured with (docs/PERFORMANCE.md)
MAX_CONTROL_RATE_HZ = 100.0
MAX_ROBOT_STEPS = 10_000_000  # robots x control steps of one run: about 1 GB of traces
MAX_ITEMS = 10_000  # obstacles, vertices, events, waypoints, profile segments
MAX_NAME_CHARS = 128
MAX_PATH_CHARS = 4096  # PATH_MAX on Linux
# The largest TOML integer (a signed 64-bit one); numpy's generators take any non-negative.
MAX_SEED = 2**63 - 1
# How old the leader's state is when a follower uses it, at most (s): the wire's longest
# period (`phalanx.wire.bounds.Period`).
MAX_COMM_DELAY_S = 10.0

_NAME = re.compile(r"[A-Za-z0-9_][A-Za-z0-9_.-]*")
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")


def check_name(value: str) -> str:
    """`value` if it is a name that can be one component of a path (`results/<name>-ours`):
    1-128 letters, digits, `_`, `-`, `.`, not starting with `-` or `.` (so never `.`,
    `..`, a hidden file or an option); ValueError otherwise.
    """
    if len(value) > MAX_NAME_CHARS or not _NAME.fullmatch(value):
        raise ValueError(
            f"expected a name: 1-{MAX_NAME_CHARS} letters, digits, '_', '-' or '.', not "
            f"starting with '-' or '.', and no path; got {value[:80]!r}"
        )
    return value


def check_path(value: str) -> str:
    """`value` if it can be a file's path (no control characters, at most 4096 characters)."""
    if len(value) > MAX_PATH_CHARS or _CONTROL.search(value):
        raise ValueError(
            f"expected a file's path: at most {MAX_PATH_CHARS} characters, no control "
            f"characters; got {value[:80]!r}"
        )
    return value


def check_robot_file(value: str) -> str:
    """`value` if it names a robot parameter file: a robot's name (a file under
    `configs/robots/`, see `check_name`) or a path with its own `.toml` extension.
    """
    if PurePath(check_path(value)).suffix == ".toml":
        return value
    try:
        return check_name(value)
    except ValueError:
        raise ValueError(
            "expected a robot's name (letters, digits, '_', '-', '.': the file "
            f"configs/robots/<name>.toml) or the path of a .toml file; got {value[:80]!r}"
        ) from None


# Names that become part of a path or a key; a path a file names; random seeds.
Name = Annotated[str, AfterValidator(check_name)]
FilePath = Annotated[str, AfterValidator(check_path)]
RobotFile = Annotated[str, AfterValidator(check_robot_file)]
Seed = Annotated[int, Field(ge=0, le=MAX_SEED)]
# A robot's id: a Zenoh key's chunk (`robot/<id>/state`) and a certificate's common name.
RobotId = Annotated[str, Field(pattern=r"^[A-Za-z0-9_-]{1,32}$")]


class Model(BaseModel):
    """Base of every config model: unknown keys rejected, values frozen, NaN and
    infinities refused (a non-finite number in a file is always a typo, never a value).
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


# --- scenario files (configs/scenarios/*.toml) -----------------------------------------


class LimitsOverride(Model):
    """Run bounds tighter than the robot's own (the paper: 0.3 m/s, 40 deg/s)."""

    v_max_mps: PositiveSpeed | None = None
    omega_max_degps: PositiveYawRate | None = None


ControllerKind = Literal["tracking", "switching", "icr", "ours"]


class ControllerConfig(Model):
    """Which follower controller runs, and its gains.

    tracking: the paper's eq. (1)-(3) in both directions; icr: the paper's eq. (7) in both
    directions; switching: the paper's strategy (tracking forwards, ICR backwards);
    ours: closed loop both ways on the exact rigid-body slot motion.
    """

    kind: ControllerKind = "ours"
    k1: Gain = 0.6
    k2: Gain = 0.6
    h_m: PositiveRange = 0.2
    gain_per_s: Gain = 1.0
    control_point_m: PositiveRange = 0.15
    compensate_delay: bool = True
    reverse_threshold_mps: NonNegativeSpeed = 0.02


class SlotConfig(Model):
    """A robot's place in the formation.

    Give either `x_m`/`y_m` (formation frame, origin at the formation leader, x along the
    formation's heading) or `l_m`/`phi_deg` relative to the robot it `follows`
    (phi counter-clockwise from that robot's heading, 180 = directly behind).
    """

    robot: RobotId
    follows: RobotId | None = None
    x_m: Coordinate | None = None
    y_m: Coordinate | None = None
    l_m: PositiveLength | None = None
    phi_deg: Angle | None = None

    @model_validator(mode="after")
    def _one_way_of_placing(self) -> Self:
        cartesian = self.x_m is not None or self.y_m is not None
        polar = self.l_m is not None or self.phi_deg is not None
        if cartesian and polar:
            raise ValueError("give either x_m/y_m or l_m/phi_deg, not both")
        if polar and (self.l_m is None or self.phi_deg is None or self.follows is None):
            raise ValueError("l_m/phi_deg need both values and `follows`")
        if cartesian and (self.x_m is None or self.y_m is None):
            raise ValueError("x_m/y_m need both values")
        return self


class FormationConfig(Model):
    """The formation's shape: one slot per robot; exactly one slot follows nobody."""

    slots: tuple[SlotConfig, ...] = Field(min_length=1, max_length=MAX_ROBOTS)

    @model_validator(mode="after")
    def _one_root(self) -> Self:
        roots = [s.robot for s in self.slots if s.follows is None]
        if len(roots) != 1:
            raise ValueError(f"exactly one slot must follow nobody, found {roots}")
        return self


class StartPose(Model):
    """A start pose (config sugar: heading in degrees)."""

    x_m: Coordinate = 0.0
    y_m: Coordinate = 0.0
    theta_deg: Angle = 0.0


# "sim" (the world process moves the robot) or the name of a driver backend, which the
# layers that open drivers check against the registry (`phalanx.drivers.BACKENDS`).
DriverKind = Annotated[str, Field(pattern=r"^[a-z][a-z0-9_]{0,31}$")]


class RobotEntry(Model):
    """One robot of the scenario."""

    id: RobotId
    start: StartPose = StartPose()
    driver: DriverKind = "sim"


class Segment(Model):
    """A piece of the leader's scripted motion: constant twist for a duration."""

    duration_s: PositiveDuration
    v_mps: SignedSpeed
    omega_degps: SignedYawRate = 0.0


class LeaderProfile(Model):
    """The leader's scripted motion (the paper's piecewise constant velocities)."""

    segments: tuple[Segment, ...] = Field(min_length=1, max_length=MAX_ITEMS)
    repeat: bool = False


class DeadlockConfig(Model):
    """The group's backward escape when no robot can lead forwards (the paper's deadlock).

    A deadlock is every robot reporting an obstacle on its path (the paper, section 1);
    for a navigating leader also: the leader blocked for `leadership.confirm_s` with no
    follower clear to take over, or in a dead end (its route leads back the way it came
    and the shape has no room to turn round). The leader stands still for the followers
    to settle onto their slots, position then heading: until every follower heard says
    it stands on its slot at its heading (`pause_until_settled`), at most `pause_s` (all
    of it with `pause_until_settled = false`; the dead-end scenarios give them up to
    12 s; 0 as the paper). Then it backs the group off
    `safe_distance_m` in formation (or until an obstacle behind stops it), then turns:
    towards its route if its map has one (to the heading nearest it along which its
    own corridor is free for twice `obstacle_range_m`), else by `turn_away_deg` (times
    the deadlocks so far at this waypoint) towards the more open side and drives
    `escape_distance_m` that way. It reverses at most `max_retries` times at one
    waypoint; after that, a leader with a map goes on retrying while the map still shows
    a way to the waypoint one robot wide (the group can fold into a column), and the
    next deadlock once it shows none stops every robot in STUCK (without a map: the next
    deadlock). A scripted leader (the paper's runs) resumes its script without turning.

    `path` backs along the path the leader actually drove (recorded from its odometry):
    the rigid formation then sweeps back through the very ground it came over, known to
    be free; `retrace` backs along the arc just driven (same curvature: the paper's
    scripted arcs); `fixed` backs with `reverse_omega_degps` (the paper: straight back),
    a navigating leader first turning the shape back to the way it came in (its last 2 m
    of path), since one caught turning on the spot would otherwise back out diagonally.
    """

    reverse_mode: Literal["path", "retrace", "fixed"] = "path"
    reverse_speed_mps: PositiveSpeed = 0.15
    reverse_omega_degps: SignedYawRate = 0.0
    pause_s: Duration = 0.0
    pause_until_settled: bool = True
    safe_distance_m: PositiveLength = 1.5
    obstacle_range_m: PositiveRange = 0.5
    turn_away_deg: Annotated[float, Field(ge=0.0, le=180.0)] = 60.0
    escape_distance_m: Length = 2.0
    max_retries: int = Field(default=3, ge=0, le=100)


class NavigationConfig(Model):
    """The navigation layer of whichever robot leads: go-to-goal over `waypoints` (world
    frame, m), or wander when there are none and no scripted `leader_profile`; reactive
    obstacle avoidance on every robot from its sonar ring; the emergency stop.

    Ranges are gaps between the robot's disc and an obstacle along a straight corridor
    `radius + body_margin_m` wide, measured in the direction of motion. A leader that
    gets no further than 0.3 m in `stall_s` folds the group into its narrowest shape,
    or, folded already (or with reshaping off), counts as blocked; a follower leaves its
    slot (AVOID) for what is nearer than `avoid_range_m` (its heading swings as its
    slot's motion bends: the leader's `deadlock.obstacle_range_m` would be too far).
    `reactive = false` switches avoidance and the emergency stop off (deadlocks and
    leadership still work; every robot is blocked within `deadlock.obstacle_range_m`):
    for scripted sensor events such as the paper's. Never on a real robot. `column_path`
    (reactive only): a follower whose slot is straight behind the one it is laid out from
    keeps to the path that robot drove, not to a slot swung out
    (`phalanx.agents.navigation.column_path`).

    `reshape`: a navigating leader may change the formation's shape (shrink it, fold it
    into a column) where the scenario's shape does not fit, and back
    (`phalanx.agents.reshape`). `prior_map`: a map_server YAML file (`phalanx.core.mapfile`)
    the fleet's map starts from (a path, or a name under `configs/maps/`).
    """

    reactive: bool = True
    column_path: bool = True
    reshape: bool = True
    prior_map: FilePath = ""
    waypoints: tuple[tuple[Coordinate, Coordinate], ...] = Field(default=(), max_length=MAX_ITEMS)
    goal_tolerance_m: PositiveLength = 0.5
    cruise_mps: PositiveSpeed = 0.2
    heading_gain_per_s: Gain = 1.0
    min_turn_radius_m: Length = 2.5
    lookahead_m: PositiveLength = 3.0
    clear_range_m: PositiveRange = 2.5
    avoid_range_m: PositiveRange = 0.2
    body_margin_m: SensorRange = 0.05
    stop_margin_m: SensorRange = 0.08
    confirm_s: PositiveDuration = 0.2
    stall_s: PositiveDuration = 10.0
    slowdown: Annotated[float, Field(gt=0.0, le=1.0)] = 0.5
    wander_period_s: PositiveDuration = 10.0
    wander_turn_deg: Annotated[float, Field(ge=0.0, le=180.0)] = 45.0


class LeadershipConfig(Model):
    """When and how leadership passes (a formation is a shape: any robot can lead).

    `handover`: the leader blocked for `confirm_s` hands over to a follower whose path
    is clear. `min_tenure_s`: no handover sooner after the last change. `loss_grace_s`:
    after the leader's state goes stale (followers hold), wait this long before electing
    a new one. `formed_m`, `formed_share`: a robot that left its slot is back in formation
    (tracked again) within the larger of `formed_m` and `formed_share` of its slot's
    distance from the robot it is laid out from (the paper's errors are shares of it).
    `join_timeout_s`: a restarted robot waits this long to hear the fleet (JOIN) first.
    """

    handover: bool = True
    confirm_s: PositiveDuration = 0.2
    min_tenure_s: Duration = 3.0
    loss_grace_s: Duration = 1.0
    formed_m: PositiveLength = 0.1
    formed_share: float = Field(default=0.1, ge=0.0, le=0.5)
    join_timeout_s: PositiveDuration = 2.0


class SensorEvent(Model):
    """A scripted sensor event (the paper's Simulink signal builder); `markers_hidden`:
    the cameras of `robots` (every robot when empty) see no marker.
    """

    kind: Literal["all_sonars_blocked", "bumper", "markers_hidden"] = "all_sonars_blocked"
    start_s: Duration
    duration_s: PositiveDuration
    robots: tuple[RobotId, ...] = Field(default=(), max_length=MAX_ROBOTS)
    range_m: PositiveRange = 0.3


class CircleObstacle(Model):
    """A circular obstacle."""

    x_m: Coordinate
    y_m: Coordinate
    radius_m: PositiveLength


class PolygonObstacle(Model):
    """A polygonal obstacle, vertices in order."""

    vertices_m: tuple[tuple[Coordinate, Coordinate], ...] = Field(
        min_length=3, max_length=MAX_ITEMS
    )


class ObstacleField(Model):
    """Circular obstacles scattered from a seed over a rectangle (a Monte-Carlo world).

    Obstacles never overlap a `keep_clear` circle (start and goal areas) and keep
    `min_gap_m` from each other; placement gives up after `count * 50` tries.
    """

    seed: Seed = 0
    count: int = Field(default=20, ge=0, le=10_000)
    radius_min_m: PositiveLength = 0.2
    radius_max_m: PositiveLength = 0.5
    x_min_m: Coordinate = 0.0
    x_max_m: Coordinate = 20.0
    y_min_m: Coordinate = -5.0
    y_max_m: Coordinate = 5.0
    min_gap_m: Length = 0.0
    keep_clear: tuple[CircleObstacle, ...] = Field(default=(), max_length=MAX_ITEMS)

    @model_validator(mode="after")
    def _ordered(self) -> Self:
        if self.radius_min_m > self.radius_max_m:
            raise ValueError("radius_min_m must not exceed radius_max_m")
        if self.x_min_m >= self.x_max_m or self.y_min_m >= self.y_max_m:
            raise ValueError("the field's rectangle is empty")
        return self


class WorldConfig(Model):
    """Static obstacles of the world, plus an optional seeded obstacle field."""

    circles: tuple[CircleObstacle, ...] = Field(default=(), max_length=MAX_ITEMS)
    polygons: tuple[PolygonObstacle, ...] = Field(default=(), max_length=MAX_ITEMS)
    field: ObstacleField | None = None
    substeps: int = Field(default=4, ge=1, le=100)
    # A robot's firmware acts on a command, and reports its sonar, a little late (AMRISim's
    # P3DX: 0.1 s and 0.2 s, docs/ROBOTS.md): the simulated robots too, by these (in whole
    # control periods). 0: at once, an ideal robot.
    command_delay_s: float = Field(default=0.0, ge=0.0, le=2.0)
    sonar_delay_s: float = Field(default=0.0, ge=0.0, le=2.0)


class NoiseConfig(Model):
    """Seeded sensor noise; zero means a perfect sensor."""

    odometry_v_std_frac: Fraction = 0.0
    odometry_omega_std_radps: Annotated[float, Field(ge=0.0, le=MAX_YAW_RATE_RADPS)] = 0.0
    sonar_std_m: SensorRange = 0.0


# --- ROS 2 (`[ros2]`, docs/ROS2.md) ------------------------------------------------------

Ros2Topic = Literal["odom", "sonar", "cmd_vel_out", "state", "tf", "tf_static", "markers"]
ROS2_TOPICS: tuple[Ros2Topic, ...] = (
    "odom", "sonar", "cmd_vel_out", "state", "tf", "tf_static", "markers",
)  # fmt: skip
# What the bridge takes from ROS 2: an operator's twists for the leader, and goals.
Ros2Input = Literal["cmd_vel", "goal_pose"]
ROS2_INPUTS: tuple[Ros2Input, ...] = ("cmd_vel", "goal_pose")
# rmw_zenoh's router (`ros2 run rmw_zenoh_cpp rmw_zenohd`) listens here by default.
ROS_ROUTER = "tcp/127.0.0.1:7447"
# A ROS name's part (a namespace's or a node's): letters, digits and '_', not a digit first.
_ROS_NAME = r"^[A-Za-z_][A-Za-z0-9_]{0,63}$"


class Ros2Config(Model):
    """The fleet as ROS 2 tools see it, through rmw_zenoh's key space (docs/ROS2.md): what
    `phalanx ros2` publishes and what `phalanx export --mcap` writes.

    `enabled`: the fleet runs a bridge (a deployment's access rules then let it publish
    its ROS keys); off by default, and nothing of ROS 2 is loaded while it is off.
    `domain_id`: ROS_DOMAIN_ID. `namespace`: put before every robot's own namespace
    (`""`: `/r1/odom`; `"lab"`: `/lab/r1/odom`, and the markers on `/lab/markers`).
    `node`: the bridge's node name. `topics`: which of `ROS2_TOPICS` are published.
    `inputs`: what it takes from ROS 2 (`cmd_vel`: an operator's twists for the robot
    that leads; `goal_pose`: a goal for a navigating leader; `[]`: nothing).
    `distro`: whose message definitions (and so type hashes) the keys carry.
    `rate_hz`: how often the bridge publishes what came in since its last round.
    `connect`: where it meets the ROS 2 nodes: their Zenoh router's endpoints, joined by
    a session of its own (empty: the session it reads the fleet on; a bridge that
    `phalanx up` or a host daemon starts then joins `ROS_ROUTER`, rmw_zenoh's default).
    """

    enabled: bool = False
    domain_id: int = Field(default=0, ge=0, le=232)
    namespace: str = Field(default="", pattern=r"^([A-Za-z_][A-Za-z0-9_]{0,63})?$")
    node: str = Field(default="phalanx_bridge", pattern=_ROS_NAME)
    topics: tuple[Ros2Topic, ...] = Field(default=ROS2_TOPICS, max_length=len(ROS2_TOPICS))
    inputs: tuple[Ros2Input, ...] = Field(default=ROS2_INPUTS, max_length=len(ROS2_INPUTS))
    distro: Literal["jazzy", "kilted"] = "jazzy"
    map_frame: str = Field(default="map", pattern=_ROS_NAME)
    rate_hz: float = Field(default=10.0, gt=0.0, le=MAX_CONTROL_RATE_HZ)
    connect: tuple[Annotated[str, Field(min_length=1, max_length=300)], ...] = Field(
        default=(), max_length=8
    )


class Scenario(Model):
    """A whole run: robots, formation, leader script or waypoints, events, world, controller.

    The leader follows `leader_profile` when one is given (the paper's runs), otherwise
    `navigation.waypoints`, otherwise it wanders.
    """

    name: Name
    description: str = ""
    robot: RobotFile = "p3dx"
    duration_s: float = Field(default=200.0, gt=0.0, le=MAX_DURATION_S)
    control_rate_hz: float = Field(default=10.0, ge=0.1, le=MAX_CONTROL_RATE_HZ)
    comm_delay_s: float = Field(default=0.1, ge=0.0, le=MAX_COMM_DELAY_S)
    seed: Seed = 0
    limits: LimitsOverride = LimitsOverride()
    controller: ControllerConfig = ControllerConfig()
    formation: FormationConfig
    robots: tuple[RobotEntry, ...] = Field(min_length=1, max_length=MAX_ROBOTS)
    leader_profile: LeaderProfile | None = None
    navigation: NavigationConfig = NavigationConfig()
    leadership: LeadershipConfig = LeadershipConfig()
    deadlock: DeadlockConfig = DeadlockConfig()
    events: tuple[SensorEvent, ...] = Field(default=(), max_length=MAX_ITEMS)
    world: WorldConfig = WorldConfig()
    noise: NoiseConfig = NoiseConfig()
    localisation: LocalisationConfig = LocalisationConfig()
    settle_s: Duration = 5.0
    initial_settle_s: Duration = 30.0
    leader_timeout_s: PositiveDuration = 0.5
    ros2: Ros2Config = Ros2Config()

    @model_validator(mode="after")
    def _at_least_a_step(self) -> Self:
        if self.duration_s < self.dt_s:
            raise ValueError(
                f"duration_s ({self.duration_s:g} s) is shorter than one control period "
                f"({self.dt_s:g} s at control_rate_hz = {self.control_rate_hz:g}): a run of "
                "no step"
            )
        return self

    @model_validator(mode="after")
    def _within_resources(self) -> Self:
        steps = len(self.robots) * self.duration_s * self.control_rate_hz
        if steps > MAX_ROBOT_STEPS:
            raise ValueError(
                f"{len(self.robots)} robots x {self.duration_s:g} s at "
                f"{self.control_rate_hz:g} Hz is {steps:.3g} robot-steps, more than the "
                f"{MAX_ROBOT_STEPS:.0e} a run may keep: shorten duration_s or use fewer robots"
            )
        return self

    @model_validator(mode="after")
    def _robots_match_slots(self) -> Self:
        ids = [r.id for r in self.robots]
        if len(set(ids)) != len(ids):
            raise ValueError(f"robot ids must be unique, got {ids}")
        slotted = {s.robot for s in self.formation.slots}
        if slotted != set(ids):
            raise ValueError(f"formation slots {sorted(slotted)} != robots {sorted(ids)}")
        for slot in self.formation.slots:
            if slot.follows is not None and slot.follows not in slotted:
                raise ValueError(f"slot {slot.robot!r} follows unknown robot {slot.follows!r}")
        white = self.noise.odometry_v_std_frac or self.noise.odometry_omega_std_radps
        if white and self.localisation.odometry.any:
            raise ValueError("give odometry errors in [noise] or [localisation.odometry], not both")
        return self

    @property
    def dt_s(self) -> float:
        """Control period, s."""
        return 1.0 / self.control_rate_hz

    def start_pose(self, robot_id: str) -> Pose2D:
        """Where `robot_id` starts, in the world frame."""
        start = next(r.start for r in self.robots if r.id == robot_id)
        return Pose2D(start.x_m, start.y_m, math.radians(start.theta_deg))
