"""What an operator asks of this robot, between two steps: `OperatorCommand`s on its
`robot/<id>/operator` key (from `phalanx ros2`: ROS 2's `cmd_vel` and `goal_pose`),
decoded, checked against the fleet's bounds and held to the sender's rate like every
other key, handed to the agent as an `OperatorInput` at each step.

The agent gets the newest twist heard, stamped when it was heard on this machine's
clock, turned into fleet time (the step's time less how long ago it came): a twist
drives a leader for `OPERATOR_TIMEOUT_S` of the operator's own time, whatever the
fleet's clock does (a lockstep world may run faster or slower than the operator's hand).
A goal is handed on once, at the step after it came.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

from phalanx.agents.inputs import OperatorInput
from phalanx.core.geometry import Twist2D, Vec2
from phalanx.wire.bounds import FleetBounds
from phalanx.wire.keys import robot_key
from phalanx.wire.messages import OperatorCommand
from phalanx.wire.transport import FleetSession


class OperatorInbox:
    """The operator's newest twist (and when it was heard) and a goal not handed on yet."""

    def __init__(
        self, fleet: str, robot_id: str, *, clock: Callable[[], float] = time.monotonic
    ) -> None:
        self.fleet, self.robot_id = fleet, robot_id
        self.heard = 0  # operator commands taken
        self.goals = 0  # goals handed on to the agent
        self._clock = clock
        self._lock = threading.Lock()
        self._twist: tuple[Twist2D, float] | None = None  # (twist, heard at)
        self._goal: Vec2 | None = None

    def attach(self, session: FleetSession, bounds: FleetBounds | None) -> None:
        """Listen on this robot's `operator` key, held to `bounds` (and to one message
        a control period, with the subscriptions' headroom).
        """
        rate_hz = None if bounds is None else 1.0 / bounds.dt_s
        key = robot_key(self.fleet, self.robot_id, "operator")
        session.subscribe(key, OperatorCommand, self._on_command, context=bounds, rate_hz=rate_hz)

    def _on_command(self, _key: str, message: OperatorCommand) -> None:
        """A valid command on this robot's key (Zenoh's thread)."""
        now = self._clock()
        with self._lock:
            self.heard += 1
            if message.twist:
                self._twist = (Twist2D(message.v_mps, message.omega_radps), now)
            if message.goal:
                self._goal = Vec2(message.goal_x_m, message.goal_y_m)

    def take(self, t_s: float) -> OperatorInput | None:
        """What to hand the agent at the step at fleet time `t_s` (None: nothing heard
        from an operator yet).
        """
        now = self._clock()
        with self._lock:
            twist, goal, self._goal = self._twist, self._goal, None
        if twist is None and goal is None:
            return None
        if goal is not None:
            self.goals += 1
        if twist is None:
            return OperatorInput(t_s, None, goal)
        return OperatorInput(t_s - max(0.0, now - twist[1]), twist[0], goal)

    def counters(self) -> dict[str, int]:
        """For the agent's status."""
        return {"operator_commands": self.heard, "operator_goals": self.goals}
