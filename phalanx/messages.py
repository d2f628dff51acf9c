"""Versioned wire messages, one model per Zenoh key (see `phalanx.transport` for keys).

Encoding and decoding (and the drop-and-count of malformed payloads) live in
`phalanx.codec`; these are the values.
"""

from __future__ import annotations

from typing import Final, Literal

from pydantic import BaseModel, ConfigDict, Field

from phalanx.geometry import Pose2D, Twist2D

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
    """

    version: Literal[1] = 1
    robot_id: str
    seq: int = Field(ge=0)
    stamp_s: float
    x_m: float
    y_m: float
    theta_rad: float
    v_mps: float
    omega_radps: float
    fsm_state: str
    obstacle: bool = False
    direction: Literal[-1, 1] = 1
    leader_id: str = ""
    epoch: int = Field(default=0, ge=0)

    @property
    def pose(self) -> Pose2D:
        """The robot's pose."""
        return Pose2D(self.x_m, self.y_m, self.theta_rad)

    @property
    def twist(self) -> Twist2D:
        """The robot's twist."""
        return Twist2D(self.v_mps, self.omega_radps)


class ClockTick(Message):
    """A lockstep tick from the world on `phalanx/<fleet>/clock`."""

    version: Literal[1] = 1
    tick: int = Field(ge=0)
    t_s: float
    dt_s: float = Field(gt=0.0)
    final: bool = False


class VelocityCommand(Message):
    """An agent's command for a simulated robot on `.../robot/<id>/cmd`."""

    version: Literal[1] = 1
    robot_id: str
    tick: int = Field(ge=0)
    stamp_s: float
    v_mps: float
    omega_radps: float


class SenseFrame(Message):
    """What the world tells a simulated robot each tick on `.../robot/<id>/sense`.

    In lockstep it is also the robot's tick: the agent answers with a VelocityCommand
    for the same `tick`. Odometry pose (m, rad) in the world frame, measured twist.
    """

    version: Literal[1] = 1
    robot_id: str
    tick: int = Field(ge=0)
    t_s: float
    dt_s: float = Field(gt=0.0)
    x_m: float
    y_m: float
    theta_rad: float
    v_mps: float
    omega_radps: float
    sonar_ranges_m: tuple[float, ...] = ()
    bumpers: tuple[bool, ...] = ()
    final: bool = False


class AgentEvent(Message):
    """A behaviour-state transition, on `.../robot/<id>/event`."""

    version: Literal[1] = 1
    robot_id: str
    t_s: float
    source: str
    target: str
    reason: str


class AgentReport(Message):
    """An agent's counters when a run ends, on `.../robot/<id>/report`."""

    version: Literal[1] = 1
    robot_id: str
    steps: int = Field(ge=0)
    saturations: int = Field(ge=0)
    accel_limited: int = Field(ge=0)
    dropped_messages: int = Field(ge=0)
    late_peer_steps: int = Field(ge=0)
    step_p50_us: float = Field(default=0.0, ge=0.0)  # control step: core, publish, telemetry
    step_p99_us: float = Field(default=0.0, ge=0.0)
    telemetry_dropped: int = Field(default=0, ge=0)
