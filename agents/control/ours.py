"""Our follower controller: closed loop in both directions, on the exact rigid-body slot
motion, with the age of the leader's state compensated.

Feedback linearisation of a control point at signed distance `d` from the axle, ahead of
it (d = +c) when the follower's target moves forwards and behind it (d = -c) when it
moves backwards (the formation reversing, or an inner slot of a turn tighter than the
slot's lateral offset):
    p = X_F + d t(theta_F),  p' = [t(theta_F), d n(theta_F)] [v, w]^T
aimed at the same point of the rigid-body target pose (rigid_body_target), whose
velocity is known in closed form. With p tracking p* exactly, the heading error obeys
    d(th_e)/dt = w*(1 - cos th_e) - (v* / d) sin th_e,
and since v* and d share a sign, v*/d = |v*|/c > 0: stable both ways. That sign flip
is exactly what the paper's tracking law (fixed h > 0) lacks in reverse. The sign follows
v* with a small hysteresis band so it cannot chatter while v* crosses zero.
"""

from __future__ import annotations

import math

from phalanx.agents.control.common import FollowerInput
from phalanx.core.geometry import Twist2D
from phalanx.core.rigid_body import predict_leader, rigid_body_target

SIGN_HYSTERESIS_MPS = 0.01


class OursController:
    """Closed-loop rigid-body tracking, forwards and backwards."""

    def __init__(
        self, *, gain_per_s: float, control_point_m: float, compensate_delay: bool = True
    ) -> None:
        self.gain_per_s = gain_per_s
        self.control_point_m = control_point_m
        self.compensate_delay = compensate_delay
        self._sign: int | None = None

    def _point_sign(self, v_star_mps: float, direction: int) -> int:
        if self._sign is None:
            self._sign = 1 if direction > 0 else -1
        if abs(v_star_mps) > SIGN_HYSTERESIS_MPS and v_star_mps * self._sign < 0.0:
            self._sign = -self._sign
        return self._sign

    def command(self, inp: FollowerInput) -> Twist2D:
        """`[v, w] = M(theta, d)^-1 (p*' + K (p* - p))`."""
        if not self.compensate_delay:
            target, ff = rigid_body_target(inp.leader, inp.leader_twist, inp.slot)
        elif inp.target is not None:
            target, ff = inp.target
        else:
            leader = inp.leader_now
            if leader is None:
                leader = predict_leader(inp.leader, inp.leader_twist, inp.leader_age_s)
            target, ff = rigid_body_target(leader, inp.leader_twist, inp.slot)
        d = self._point_sign(ff.v_mps, inp.direction) * self.control_point_m
        # (plain floats: this runs for every follower every step)
        tf_x, tf_y = math.cos(inp.follower.theta_rad), math.sin(inp.follower.theta_rad)
        tt_x, tt_y = math.cos(target.theta_rad), math.sin(target.theta_rad)
        p_x, p_y = inp.follower.x_m + d * tf_x, inp.follower.y_m + d * tf_y
        p_star_x, p_star_y = target.x_m + d * tt_x, target.y_m + d * tt_y
        # p*' = v* t(theta*) + d w* n(theta*), n = t rotated +90 deg
        w_x = ff.v_mps * tt_x - d * ff.omega_radps * tt_y
        w_y = ff.v_mps * tt_y + d * ff.omega_radps * tt_x
        w_x += self.gain_per_s * (p_star_x - p_x)
        w_y += self.gain_per_s * (p_star_y - p_y)
        v = w_x * tf_x + w_y * tf_y
        omega = (-w_x * tf_y + w_y * tf_x) / d
        return Twist2D(v, omega)

    def reset(self) -> None:
        """Forget which side of the axle the control point is on."""
        self._sign = None
