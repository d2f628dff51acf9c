"""Everything one robot's brain is made of, made and wired together once: its view of the
shape, its senses and route planner, its memories, and the behaviour table that maps
each behaviour state to the object that drives it.

The scenario is taken apart here, and nowhere below: a behaviour is given the settings it
reads (navigation's `NavSettings`, a table of the scenario, the control step), never the
whole scenario.

Adding a behaviour: write it (a `Behaviour` subclass, in `phalanx.agents.behaviours`),
give it the parts and settings it needs here, and put it in the table under the state
(or states) it drives; the transitions into and out of that state go in
`phalanx.agents.behaviours.stack`.
"""

from __future__ import annotations

import math

from phalanx.agents.behaviours.base import Behaviour, EmergencyStop, StandStill
from phalanx.agents.behaviours.follower import Avoid, Track
from phalanx.agents.behaviours.leader import (
    DeadlockReverse,
    DeadlockTurn,
    GoToGoal,
    Scripted,
    SteeredParts,
    Teleop,
    Wander,
)
from phalanx.agents.control import make_controller
from phalanx.agents.memory import BlockedTimers, Progress, Route, StartUp, StopsBefore
from phalanx.agents.navigation import (
    Breadcrumbs,
    Course,
    FleetMap,
    NavSettings,
    Plan,
    RoutePlanner,
    Steering,
    Trail,
    plan_of,
)
from phalanx.agents.perception import SonarGeometry
from phalanx.agents.reshape import Arrived, Reshape, ShapeKeeper
from phalanx.agents.sensing import Senses
from phalanx.agents.shape import Shape
from phalanx.core.config import Scenario
from phalanx.core.formation import Formation
from phalanx.core.geometry import Pose2D, Vec2
from phalanx.core.limits import KinematicLimits
from phalanx.core.mapfile import GridMap
from phalanx.core.robot_params import RobotParams
from phalanx.core.shapes import NOMINAL_KEY, ShapeBook, ShapeKey
from phalanx.core.states import State


class Parts:
    """One robot's brain, wired (see the module docstring)."""

    def __init__(
        self,
        robot_id: str,
        scenario: Scenario,
        robot: RobotParams,
        formation: Formation,
        limits: KinematicLimits,
        prior: GridMap | None = None,
    ) -> None:
        self.scenario = scenario
        self.plan: Plan = plan_of(scenario)
        nav = scenario.navigation
        # What navigation reads of the scenario: its behaviours and senses are given this.
        self.settings = NavSettings(nav, scenario.deadlock, self.plan, scenario.dt_s)
        self.shape = Shape(
            robot_id, formation, radius_m=robot.radius_m, nav=nav, limits=limits,
            dt_s=scenario.dt_s,
        )  # fmt: skip
        self.progress = Progress()
        self.route = Route(nav.waypoints)
        self.blocked = BlockedTimers()
        self.steering = Steering()
        self.course = Course(Breadcrumbs(2.0 * scenario.deadlock.safe_distance_m))
        # The path of the robot this one's slot is laid out from (a column keeps to it).
        self.trail = Trail() if nav.column_path and nav.reactive else None
        self.startup = StartUp()
        self.stops = StopsBefore()
        self.planner = RoutePlanner(keep_off_m=self.shape.half_span_m, robot_id=robot_id)
        if self.plan != "scripted" and nav.reactive:
            self.planner.share(fleet_map(scenario, robot, formation, prior))
        self.keeper = ShapeKeeper(
            ShapeBook(formation), robot.radius_m, enabled=nav.reshape and self.plan == "goto"
        )
        self._applied: ShapeKey = NOMINAL_KEY
        self.senses = Senses(
            robot_id, self.settings, sonar=SonarGeometry.from_params(robot), shape=self.shape,
            limits=limits, planner=self.planner, progress=self.progress, route=self.route,
            crumbs=self.course.crumbs, fold=self.keeper.fold,
        )  # fmt: skip
        self.reverse = DeadlockReverse(
            self.settings, shape=self.shape, course=self.course, progress=self.progress
        )
        self.turn = DeadlockTurn(
            self.settings, shape=self.shape, planner=self.planner, progress=self.progress,
            route=self.route, course=self.course, blocked=self.blocked,
        )  # fmt: skip
        self.avoid = Avoid(
            nav, dt_s=scenario.dt_s, shape=self.shape, limits=limits, steering=self.steering
        )
        steered = SteeredParts(self.settings, self.shape, limits, self.steering, self.course)
        # (a leader going to waypoints drives on with its navigation while it reshapes)
        go = None
        if scenario.leader_profile is None and self.plan != "wander":
            go = GoToGoal(
                steered, planner=self.planner, progress=self.progress, route=self.route,
                keeper=self.keeper,
            )  # fmt: skip
        self.reshape = Reshape(self.keeper, self.shape, dt_s=scenario.dt_s, drive=go)
        self.estop = EmergencyStop()
        seed = scenario.seed + formation.robot_ids.index(robot_id)
        self.behaviours = self._table(robot_id, limits, Wander(steered, seed=seed), go)

    def _table(
        self, robot_id: str, limits: KinematicLimits, wander: Wander, go: GoToGoal | None
    ) -> dict[str, Behaviour]:
        """The behaviour of each state (`go`: the leader's way to its waypoints)."""
        scenario = self.scenario
        navigate: Behaviour = go or wander
        if scenario.leader_profile is not None:
            navigate = Scripted(
                scenario.leader_profile, progress=self.progress, course=self.course,
                dt_s=scenario.dt_s,
            )  # fmt: skip
        track = self.track = Track(
            robot_id, dt_s=scenario.dt_s, shape=self.shape, limits=limits,
            controller=make_controller(scenario.controller),
            trail=self.trail,
        )  # fmt: skip
        still = StandStill()
        table: dict[str, Behaviour] = {
            State.NAVIGATE: navigate,
            State.WANDER: navigate if self.plan == "scripted" else wander,
            State.DEADLOCK_REVERSE: self.reverse,
            State.DEADLOCK_TURN: self.turn,
            State.FORMATION_TRACK: track,
            State.FORMATION_REVERSE: track,
            State.AVOID: self.avoid,
            State.RESHAPE: self.reshape,
            State.ARRIVED: Arrived(self.reshape),
            State.HOLD: StandStill(emergency=True),
            State.EMERGENCY_STOP: self.estop,
            State.TELEOP: Teleop(self.shape, limits),
        }
        return {state: table.get(state, still) for state in State}

    def apply_shape(self) -> None:
        """Take the shape in effect (`keeper.key`) wherever it is used: the slots this
        robot tracks and steers the group by, where the sonar expects the others (both
        shapes' slots while between two), the route's keep-off distance.
        """
        key = self.keeper.key
        if key == self._applied:
            return
        book, previous = self.keeper.book, self._applied
        self._applied = key
        self.shape.adopt(book.formation(key))
        if (key.source, key.target, key.settled) != (
            previous.source,
            previous.target,
            previous.settled,
        ):
            ends = {key.target} if key.settled else {key.source, key.target}
            here = book.shapes
            self.senses.remask(tuple(_offsets(here[s], self.shape.robot_id) for s in sorted(ends)))
        self.planner.keep_off_m = self.shape.half_span_m

    def weigh_shapes(self, pose: Pose2D, t_s: float, *, navigating: bool) -> None:
        """The leader weighs the shapes for the way to its next waypoint while it
        navigates, and otherwise only gauges whether the scenario's shape fits the way.
        """
        waypoints = self.route.waypoints
        if self.keeper.enabled and self.progress.waypoint < len(waypoints):
            goal = self.course.escape or Vec2(*waypoints[self.progress.waypoint])
            weigh = self.keeper.decide if navigating else self.keeper.gauge
            weigh(self.planner.map, pose, goal, t_s, self.planner.points)

    def retries_left(self, pose: Pose2D, *, deadlocked: bool) -> bool:
        """Whether a deadlock may be met with another reverse, turn and retry: while
        `deadlock.max_retries` are not used up at this waypoint, and after that while
        the map still shows a way to it one robot wide (the group can fold into a
        column); STUCK is for when the map proves there is none.
        """
        if self.progress.deadlocks < self.settings.deadlock.max_retries:
            return True
        waypoints = self.route.waypoints
        if not deadlocked or self.plan != "goto" or self.progress.waypoint >= len(waypoints):
            return False
        goal = Vec2(*waypoints[self.progress.waypoint])
        return self.planner.way_exists(pose, goal, footprint_m=self.shape.radius_m)

    def advance_waypoints(self, pose: Pose2D) -> None:
        """The leader's waypoint bookkeeping: a reached waypoint resets the retries (and
        the escape point a dead end left, once reached or passed by).
        """
        progress, course, waypoints = self.progress, self.course, self.route.waypoints
        if self.plan != "goto":
            return
        near_m = self.settings.nav.goal_tolerance_m
        if course.escape is not None and (pose.position - course.escape).norm() < near_m:
            course.escape = None
        while (
            progress.waypoint < len(waypoints) and _to(pose, waypoints[progress.waypoint]) < near_m
        ):
            progress.waypoint += 1
            progress.deadlocks = 0
            course.escape = None

    def take_goal(self, goal: Vec2) -> bool:
        """An operator's goal, in place of the waypoints not reached yet (a fresh target:
        no deadlock counted at it yet, no escape point, a route planned anew); taken by
        a navigating leader only, and only on its map if it has one. Whether it was.
        """
        grid = self.planner.map
        if self.plan != "goto" or (grid is not None and not grid.covers(goal)):
            return False
        self.route.replace_rest(self.progress.waypoint, (goal.x_m, goal.y_m))
        self.progress.deadlocks = 0
        self.course.escape = None
        self.planner.forget_carrot()
        return True


def _to(pose: Pose2D, point: tuple[float, float]) -> float:
    return math.hypot(point[0] - pose.x_m, point[1] - pose.y_m)


def _offsets(slots: dict[str, Vec2], robot_id: str) -> dict[str, Vec2]:
    here = slots[robot_id]
    return {r: p - here for r, p in slots.items()}


def fleet_map(
    scenario: Scenario, robot: RobotParams, formation: Formation, prior: GridMap | None
) -> FleetMap:
    """The fleet's shared map of a navigating scenario: centred where the formation's
    first robot starts (every robot of the fleet alike), from `prior` if given.
    """
    start = scenario.robots[0].start
    return FleetMap(
        Vec2(start.x_m, start.y_m),
        sonar=SonarGeometry.from_params(robot),
        order=formation.robot_ids,
        prior=prior,
    )
