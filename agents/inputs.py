"""What a control step starts from: the robot's own readings, and its view of the fleet
(who leads, whom it tracks and that robot's latest state).
"""

from __future__ import annotations

from dataclasses import dataclass

from phalanx.agents.leadership import LeadershipChange, LiveFlags
from phalanx.agents.perception import MaskedEchoes, SonarEchoes
from phalanx.core.fixes import PoseFix, RelativeFix
from phalanx.core.frozen import quick_init
from phalanx.core.peers import PeerState, Scan
from phalanx.core.robot import Odometry, RobotStatus


@quick_init
@dataclass(frozen=True, slots=True)
class Observation:
    """What a robot senses this step (from its driver, or the simulated world): odometry,
    its status, and the positioning measurements that arrived since the last step (pose
    fixes, relative measurements of other robots), each stamped when it was taken, and
    the sonar scans the fleet shared since the last step (`phalanx.agents.fleetmap`).

    `sonar`: the sonar ranges of `status` already read as geometry, and `masked`: that
    reading with the formation's robots masked out for this robot's step (the batch
    runner does both for every robot in one pass, `phalanx.agents.masking`); when None,
    the agent works them out itself. `near`: the robots near enough to this one to matter
    for keeping apart (a large fleet's batch runner sorts them out for all robots at
    once); when None, every robot heard is checked.
    """

    odometry: Odometry
    status: RobotStatus
    sonar: SonarEchoes | None = None
    masked: MaskedEchoes | None = None
    fixes: tuple[PoseFix, ...] = ()
    relative: tuple[RelativeFix, ...] = ()
    scans: tuple[Scan, ...] = ()  # the fleet's sonar scans for the shared map (last step's)
    near: frozenset[str] | None = None

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
        )


@quick_init
@dataclass(frozen=True, slots=True)
class FleetView:
    """A robot's view of its fleet this step: the flags heard lately (`live`), the
    change by which it took the lead this step (if it did), who leads, whom it tracks
    (None while it leads) and that robot's state, if fresh; and the leader's state
    (`head`), if fresh and the leader is not the robot tracked.
    """

    live: LiveFlags
    took: LeadershipChange | None
    is_leader: bool
    leader_id: str
    tracked_id: str | None
    lead: PeerState | None
    head: PeerState | None = None

    @property
    def anchor(self) -> PeerState | None:
        """The state this robot's slot is laid out from: the formation leader's, when
        it is fresh (a slot relative to the whole shape's head does not swing with the
        robots between, whose own corrections would otherwise add up down a chain), or
        the tracked robot's.
        """
        return self.head if self.head is not None else self.lead
