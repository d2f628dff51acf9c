"""The paper's controllers: the closed-loop tracking law, eqs. (1)-(3); the geometric
ICR law, eq. (7); and the switching strategy of section 4 between them.
"""

from __future__ import annotations

import math

from phalanx.agents.control.common import FollowerInput
from phalanx.core.geometry import Twist2D


class PaperTracking:
    """Eqs. (1)-(3): feedback linearisation about a point `h_m` ahead of the axle.

    Translated to our slot convention (phi_paper = phi + pi, so the paper's
    `X_L - l cos(phi + theta_L)` is our slot point `X_L + R(theta_L) s`). Derived again
    from the target velocity of the slot point in the follower's frame:
        v = cos(th_e) v_L - l sin(phi + th_e) w_L + k1 x_e
        w = [sin(th_e) v_L + l cos(phi + th_e) w_L + k2 y_e] / h
    The v row is the paper's eq. (1) exactly. In the w row the paper prints
    `+ l cos(phi_p + th_e) w_L / h - k2 y_e / h`; with phi_p = phi + pi the first term is
    ours with the opposite sign and the second drives y_e away from zero, i.e. the printed
    signs describe an unstable tracker under any consistent frame, so we use the derived
    (stable) signs.

    Why it fails in reverse: the law leaves the heading as internal dynamics
    d(th_e)/dt = -(v_L / h) sin(th_e), stable for v_L > 0 and unstable for v_L < 0, so a
    reversing follower jackknifes.
    """

    def __init__(self, *, k1: float, k2: float, h_m: float) -> None:
        self.k1, self.k2, self.h_m = k1, k2, h_m

    def command(self, inp: FollowerInput) -> Twist2D:
        """Eq. (1) with the errors of eqs. (2)-(3)."""
        leader, follower, s = inp.leader, inp.follower, inp.slot
        th_e = leader.theta_rad - follower.theta_rad
        slot_point = leader.to_world(s)
        x_e, y_e = (follower.to_body(slot_point).x_m, follower.to_body(slot_point).y_m)
        v_l, w_l = inp.leader_twist.v_mps, inp.leader_twist.omega_radps
        # -l sin(phi + th_e) = -(s_y cos th_e + s_x sin th_e); l cos(phi + th_e) likewise.
        lat = s.x_m * math.cos(th_e) - s.y_m * math.sin(th_e)
        lon = s.y_m * math.cos(th_e) + s.x_m * math.sin(th_e)
        v = math.cos(th_e) * v_l - lon * w_l + self.k1 * x_e
        w = (math.sin(th_e) * v_l + lat * w_l + self.k2 * y_e) / self.h_m
        return Twist2D(v, w)

    def reset(self) -> None:
        """Stateless."""


class PaperIcr:
    """Eq. (7) without the division: `v_F = v_L - w_L s_y`, `w_F = w_L`.

    Open loop: it keeps a follower that starts on its slot there only when the slot has
    no longitudinal offset (s_x = 0, abreast) or the leader does not turn; otherwise the
    relative position circles about (0, s_y) at the leader's yaw rate, because the
    relation ignores s_x.
    """

    def command(self, inp: FollowerInput) -> Twist2D:
        """Eq. (7)."""
        w_l = inp.leader_twist.omega_radps
        return Twist2D(inp.leader_twist.v_mps - w_l * inp.slot.y_m, w_l)

    def reset(self) -> None:
        """Stateless."""


class PaperSwitching:
    """Section 4: the tracking law while the formation moves forwards, ICR backwards."""

    def __init__(self, *, k1: float, k2: float, h_m: float) -> None:
        self.tracking = PaperTracking(k1=k1, k2=k2, h_m=h_m)
        self.icr = PaperIcr()

    def command(self, inp: FollowerInput) -> Twist2D:
        """Tracking for direction +1, ICR for -1."""
        law = self.tracking if inp.direction > 0 else self.icr
        return law.command(inp)

    def reset(self) -> None:
        """Stateless."""
