"""What a control step starts from: the robot's own readings, and its view of the fleet
(who leads, whom it tracks, that robot's latest state and where it is now, and this
robot's slot), worked out once per step and read by every stage after.
"""

from __future__ import annotations

from dataclasses import dataclass

from phalanx.agents.leadership import LeadershipChange, LiveFlags
from phalanx.agents.perception import MaskedEchoes, SonarEchoes
from phalanx.core.fixes import PoseFix, RelativeFix
from phalanx.core.frozen import quick_init
from phalanx.core.geometry import Pose2D, Twist2D, Vec2
from phalanx.core.peers import PeerState, Scan
from phalanx.core.rigid_body import predict_leader
from phalanx.core.robot import Odometry, RobotStatus

# An operator's twist drives the robot until it is this old (s on the fleet clock, from
# when the robot heard it): commands that stop coming hand the leader back to its plan.
OPERATOR_TIMEOUT_S = 0.5


@quick_init
@dataclass(frozen=True, slots=True)
class OperatorInput:
    """What an operator asks of the robot (`phalanx ros2`: ROS 2's `cmd_vel` and
    `goal_pose`), as the runtime hands it in at a step: `twist`, the last twist heard
    (m/s, rad/s, before every limit; None: none yet), heard at `stamp_s` on the fleet
    clock (it drives a leader while younger than `OPERATOR_TIMEOUT_S`); `goal`, a goal
    heard since the last step (world frame, m; None: none), which a navigating leader
    takes in place of the waypoints it has not reached.
    """

    stamp_s: float
    twist: Twist2D | None = None
    goal: Vec2 | None = None

    def drives(self, t_s: float) -> bool:
        """Whether its twist is young enough at `t_s` to drive by."""
        return self.twist is not None and t_s - self.stamp_s < OPERATOR_TIMEOUT_S - 1e-9


@quick_init
@dataclass(frozen=True, slots=True)
class Observation:
    """What a robot senses this step (from its driver, or the simulated world): odometry,
    its status, and the positioning measurements that arrived since the last step (pose
    fixes, relative measurements of other robots), each stamped when it was taken, and
    the sonar scans the fleet shared since the last step
    (`phalanx.agents.navigation.fleet_map`).

    `sonar`: the sonar ranges of `status` already read as geometry, and `masked`: that
    reading with the formation's robots masked out for this robot's step (the batch
    runner does both for every robot in one pass, `phalanx.agents.masking`); when None,
    the agent works them out itself. `near`: the robots near enough to this one to matter
    for keeping apart (a large fleet's batch runner sorts them out for all robots at
    once); when None, every robot heard is checked. `operator`: what an operator asks of
    the robot (None: nothing heard from one).
    """

    odometry: Odometry
    status: RobotStatus
    sonar: SonarEchoes | None = None
    masked: MaskedEchoes | None = None
    fixes: tuple[PoseFix, ...] = ()
    relative: tuple[RelativeFix, ...] = ()
    scans: tuple[Scan, ...] = ()  # the fleet's sonar scans for the shared map (last step's)
    near: frozenset[str] | None = None
    operator: OperatorInput | None = None

    def with_odometry(self, odometry: Odometry) -> Observation:
        """The observation with `odometry` (itself when that is already its own)."""
        if odometry is self.odometry:
            return self
        return Observation(
            odometry,
            self.status,
            self.sonar,
            self.masked,
            self.fixes,
            self.relative,
            self.scans,
            self.near,
            self.operator,
        )

    def with_masked(self, masked: MaskedEchoes) -> Observation:
        """The observation with `masked` (`dataclasses.replace`, without its cost)."""
        return Observation(
            self.odometry,
            self.status,
            self.sonar,
            masked,
            self.fixes,
            self.relative,
            self.scans,
            self.near,
            self.operator,
        )


@quick_init
@dataclass(frozen=True, slots=True)
class FleetView:
    """A robot's view of its fleet this step: the flags heard lately (`live`), the
    change by which it took the lead this step (if it did), who leads, whom it tracks
    (None while it leads) and that robot's state, if fresh; and the leader's state
    (`head`), if fresh and the leader is not the robot tracked.

    `lead_now` and `head_now`: those states' poses dead-reckoned to the step's time
    (`now`); `slot`: this robot's rigid slot target and its feed-forward twist, laid out
    from the `anchor` where it is now (None without one).
    """

    live: LiveFlags
    took: LeadershipChange | None
    is_leader: bool
    leader_id: str
    tracked_id: str | None
    lead: PeerState | None
    head: PeerState | None = None
    lead_now: Pose2D | None = None
    head_now: Pose2D | None = None
    slot: tuple[Pose2D, Twist2D] | None = None

    @property
    def anchor(self) -> PeerState | None:
        """The state this robot's slot is laid out from: the formation leader's, when
        it is fresh (a slot relative to the whole shape's head does not swing with the
        robots between, whose own corrections would otherwise add up down a chain), or
        the tracked robot's.
        """
        return self.head if self.head is not None else self.lead

    @property
    def anchor_now(self) -> Pose2D | None:
        """The anchor's pose dead-reckoned to the step's time."""
        return self.head_now if self.head is not None else self.lead_now


def now(state: PeerState | None, t_s: float) -> Pose2D | None:
    """`state`'s pose dead-reckoned along its twist to fleet time `t_s` (None: none).
    The one place a step predicts where another robot is: the agent calls it once per
    robot it reads, and every stage reads the result from the `FleetView`.
    """
    if state is None:
        return None
    return predict_leader(state.pose, state.twist, max(0.0, t_s - state.stamp_s))
