"""A formation is a shape: slot positions in a formation frame plus who follows whom.

The formation frame moves with the group: origin at the root robot's slot, x along the
formation's heading. In a rigid formation every robot has that heading, so the slot of
any robot relative to any other, in the other's body frame, is the difference of their
slot positions. That is what lets leadership pass to any robot (docs/ARCHITECTURE.md, conventions).
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cached_property

from phalanx.core.config import FormationConfig, Scenario
from phalanx.core.errors import ConfigError
from phalanx.core.geometry import Pose2D, Vec2, polar_to_slot, slot_to_polar


@dataclass(frozen=True)
class Formation:
    """Resolved formation: slot of every robot and the tracking tree."""

    positions: Mapping[str, Vec2]
    parents: Mapping[str, str | None]

    @property
    def root(self) -> str:
        """The robot that follows nobody (the formation leader)."""
        return next(r for r, p in self.parents.items() if p is None)

    @cached_property
    def robot_ids(self) -> tuple[str, ...]:
        """Every robot, in definition order."""
        return tuple(self.positions)

    @cached_property
    def rank(self) -> Mapping[str, int]:
        """Every robot's place in definition order (0 first)."""
        return {r: i for i, r in enumerate(self.positions)}

    def leader_of(self, robot_id: str) -> str | None:
        """The robot `robot_id` tracks, or None for the root."""
        return self.parents[robot_id]

    def followers_of(self, robot_id: str) -> tuple[str, ...]:
        """The robots that track `robot_id`."""
        return self._followers.get(robot_id, ())

    @cached_property
    def _followers(self) -> Mapping[str, tuple[str, ...]]:
        children: dict[str, list[str]] = {}
        for r, p in self.parents.items():
            if p is not None:
                children.setdefault(p, []).append(r)
        return {p: tuple(c) for p, c in children.items()}

    def neighbours(self, robot_id: str) -> tuple[str, ...]:
        """Robots joined to `robot_id` in the follow tree, either way (its parent first)."""
        parent = self.parents[robot_id]
        return ((parent,) if parent is not None else ()) + self.followers_of(robot_id)

    def tree_path(self, start: str, goal: str) -> tuple[str, ...]:
        """The robots on the follow tree's path from `start` to `goal`, `goal` included and
        `start` not. Re-rooting the tree at `goal` makes the first of them `start`'s parent.
        """
        towards = self._towards.get(goal, {})
        if not towards and goal in self.parents:  # (one pass per goal for every robot)
            towards = self._towards[goal] = self._steps_towards(goal)
        if start not in towards:
            raise ValueError(f"{goal!r} is not connected to {start!r} in the follow tree")
        path, here = [], start
        while here != goal:
            here = towards[here]
            path.append(here)
        return tuple(path)

    @cached_property
    def _towards(self) -> dict[str, dict[str, str]]:
        """Per goal asked for so far, `_steps_towards` it."""
        return {}

    def _steps_towards(self, goal: str) -> dict[str, str]:
        """Every robot connected to `goal` (itself included) and its neighbour one step
        closer to it on the follow tree (`goal`'s own: itself).
        """
        towards, frontier = {goal: goal}, deque([goal])
        while frontier:
            here = frontier.popleft()
            for nxt in self.neighbours(here):
                if nxt not in towards:
                    towards[nxt] = here
                    frontier.append(nxt)
        return towards

    def reroot(self, leader: str) -> dict[str, str | None]:
        """The follow tree re-rooted at `leader`: every robot's parent on its path there."""
        return {r: (None if r == leader else self.tree_path(r, leader)[0]) for r in self.parents}

    def slot_of(self, follower: str, leader: str) -> Vec2:
        """`follower`'s slot in `leader`'s body frame, m (any pair, not only tree edges)."""
        return self.positions[follower] - self.positions[leader]

    def polar_of(self, follower: str, leader: str) -> tuple[float, float]:
        """(l in m, phi in rad) of `follower` relative to `leader`."""
        return slot_to_polar(self.slot_of(follower, leader))

    def slot_pose(self, robot_id: str, root_pose: Pose2D) -> Pose2D:
        """Where `robot_id` sits in a rigid formation whose root is at `root_pose`."""
        position = root_pose.to_world(self.positions[robot_id] - self.positions[self.root])
        return Pose2D(position.x_m, position.y_m, root_pose.theta_rad)


def resolve_formation(config: FormationConfig) -> Formation:
    """Turn slot definitions (cartesian or polar relative to a parent) into positions."""
    slots = {s.robot: s for s in config.slots}
    positions: dict[str, Vec2] = {}
    resolving: set[str] = set()

    def place(robot: str) -> Vec2:
        if robot in positions:
            return positions[robot]
        if robot in resolving:
            raise ConfigError(f"formation: the follow chain through {robot!r} is a cycle")
        resolving.add(robot)
        slot = slots[robot]
        if slot.l_m is not None and slot.phi_deg is not None and slot.follows is not None:
            offset = polar_to_slot(slot.l_m, math.radians(slot.phi_deg))
            positions[robot] = place(slot.follows) + offset
        else:
            positions[robot] = Vec2(slot.x_m or 0.0, slot.y_m or 0.0)
        return positions[robot]

    for robot in slots:
        place(robot)
    ordered = {robot: positions[robot] for robot in slots}
    return Formation(positions=ordered, parents={s.robot: s.follows for s in config.slots})


def scenario_formation(scenario: Scenario) -> Formation:
    """The resolved formation of a scenario."""
    return resolve_formation(scenario.formation)
