"""What the world process sends each simulated robot at a tick: its sense frame (the
robot's odometry and sensors from the world, its clock in lockstep) and the positioning
measurements the simulated sensors made of it (in the frame, or on the robot's `fix` and
`relative` keys when the robot is on a driver and keeps its own clock).
"""

from __future__ import annotations

from collections.abc import Sequence

from phalanx.core.fixes import PoseFix, RelativeFix
from phalanx.runtime.positioning import (
    fix_message,
    flatten_fixes,
    flatten_relative,
    relative_message,
)
from phalanx.simulator.world import World
from phalanx.wire.codec import encode
from phalanx.wire.keys import robot_key
from phalanx.wire.messages import RobotState, SenseFrame
from phalanx.wire.transport import FleetSession

Flat = tuple[tuple[float, ...], tuple[float, ...]]  # a frame's fixes and relative groups


def sense_frame(
    world: World,
    rid: str,
    k: int,
    dt_s: float,
    *,
    final: bool = False,
    positioning: Flat = ((), ()),
    peers: tuple[RobotState, ...] = (),
) -> SenseFrame:
    """Robot `rid`'s frame for tick `k` (at k * dt_s s), from the world as it is now,
    carrying `peers` (the other robots' states, in lockstep).
    """
    odo, status = world.odometry(rid), world.status(rid)
    return SenseFrame(
        robot_id=rid,
        tick=k,
        t_s=float(k * dt_s),
        dt_s=dt_s,
        x_m=odo.pose.x_m,
        y_m=odo.pose.y_m,
        theta_rad=odo.pose.theta_rad,
        v_mps=odo.twist.v_mps,
        omega_radps=odo.twist.omega_radps,
        sonar_ranges_m=status.sonar_ranges_m,
        bumpers=status.bumpers,
        final=final,
        fixes=positioning[0],
        relative=positioning[1],
        peers=peers,
    )


def send_final(
    session: FleetSession, world: World, fleet: str, robots: Sequence[str], k: int, dt_s: float
) -> None:
    """The final frame (tick `k`, the run's end) to each of `robots`."""
    for rid in robots:
        frame = sense_frame(world, rid, k, dt_s, final=True)
        session.publish(robot_key(fleet, rid, "sense"), frame, reliable_block=True)


def lockstep_frame_bytes(world: World, ids: Sequence[str], dt_s: float) -> int:
    """The packed size of the largest lockstep frame `world` sends its fleet `ids`:
    every other robot's state in it, each at its largest (with a covariance).
    """
    states = tuple(
        RobotState(
            robot_id=rid, seq=0, stamp_s=0.0, x_m=0.0, y_m=0.0, theta_rad=0.0, v_mps=0.0,
            omega_radps=0.0, fsm_state="FORMATION_TRACK", cov=(1.0, 0.0, 0.0, 1.0, 0.0, 1.0),
            leader_id=ids[0], formation_leader_id=ids[0],
        )
        for rid in ids[1:]
    )  # fmt: skip
    return len(encode(sense_frame(world, ids[0], 1, dt_s, peers=states), "packed"))


def publish_positioning(
    session: FleetSession,
    fleet: str,
    rid: str,
    fixes: Sequence[PoseFix],
    relative: Sequence[RelativeFix],
    ids: Sequence[str],
    *,
    epoch_s: float | None,
) -> Flat:
    """The robot's simulated positioning measurements due now: flattened for its sense
    frame or, for a robot on a driver (a run with an epoch, Unix time), published on its
    `fix` and `relative` keys as a motion-capture system and its camera would (then the
    frame carries none).
    """
    if epoch_s is None:
        return flatten_fixes(fixes), flatten_relative(relative, ids)
    for fix in fixes:
        session.publish(robot_key(fleet, rid, "fix"), fix_message(rid, fix, epoch_s=epoch_s))
    for rel in relative:
        message = relative_message(rid, rel, epoch_s=epoch_s)
        session.publish(robot_key(fleet, rid, "relative"), message)
    return (), ()
