"""Where robots are, measured, on their own keys: an absolute pose fix (`fix`: motion
capture, or the world simulating it), another robot seen by this one's camera
(`relative`), and where a simulator says a robot really is (`truth`). Each is stamped in
Unix time, when it was taken; the receiver turns it into fleet time with the run's epoch.
"""

from __future__ import annotations

import math
from typing import Literal

from pydantic import Field

from phalanx.wire.bounds import RobotId, Speed, UnixStamp, YawRate
from phalanx.wire.messages import Message


class StampedPose(Message):
    """Robot `robot_id`'s pose in the fleet's world frame (m, rad), taken at `stamp_s` in
    Unix time: what a pose fix and a simulator's true pose both say.
    """

    version: Literal[1] = 1
    robot_id: RobotId
    stamp_s: UnixStamp
    x_m: float = Field(ge=-1e4, le=1e4)
    y_m: float = Field(ge=-1e4, le=1e4)
    theta_rad: float = Field(ge=-2 * math.pi, le=2 * math.pi)


class PoseFixMessage(StampedPose):
    """An absolute pose fix of robot `robot_id` on `.../robot/<id>/fix` (a motion-capture
    bridge, `phalanx mocap`, or the world process simulating one for robots on drivers).

    Pose in the fleet's world frame (m, rad), taken at `stamp_s` in Unix time (the
    receiving agent turns it into fleet time with its epoch), with the source's standard
    deviations (`std_m` on x and y, `std_rad` on the heading).
    """

    std_m: float = Field(gt=0.0, le=10.0)
    std_rad: float = Field(gt=0.0, le=math.pi)


class TruthMessage(StampedPose):
    """Where a simulator says robot `robot_id` really is, on `.../robot/<id>/truth`: the
    robot's agent passes on what its driver reads from the simulator (AMRISim's SIMSTAT),
    for the run's record. No agent steers by it.

    Pose in the fleet's world frame (m, rad) with the robot's twist, taken at `stamp_s` in
    Unix time (the recorder turns it into fleet time with the run's epoch); `source` names
    the simulator, `clock_rate` is how fast its clock has run (simulated seconds a real
    second, since the robot connected).
    """

    v_mps: Speed
    omega_radps: YawRate
    source: str = Field(max_length=32, pattern=r"^[A-Za-z0-9 ._-]*$")
    clock_rate: float = Field(default=1.0, ge=0.0, le=100.0)  # simulated s a real s


class RelativeFixMessage(Message):
    """Robot `target_id` seen from robot `robot_id` on `.../robot/<id>/relative` (the world
    process simulating the camera of a robot on a driver): range (m) and bearing (rad,
    counter-clockwise from the robot's heading) of the target's centre and, when
    `std_heading_rad` > 0, the target's heading relative to the robot's; taken at
    `stamp_s` in Unix time.
    """

    version: Literal[1] = 1
    robot_id: RobotId
    target_id: RobotId
    stamp_s: UnixStamp
    range_m: float = Field(ge=0.0, le=100.0)
    bearing_rad: float = Field(ge=-2 * math.pi, le=2 * math.pi)
    heading_rad: float = Field(default=0.0, ge=-2 * math.pi, le=2 * math.pi)
    std_range_m: float = Field(gt=0.0, le=10.0)
    std_bearing_rad: float = Field(gt=0.0, le=math.pi)
    std_heading_rad: float = Field(default=0.0, ge=0.0, le=math.pi)
