"""The pose filter's math: a 3-state extended Kalman filter (x, y, theta in the world
frame) predicting with wheel-odometry increments and correcting with any measurement of
the pose, with the two wheels' scale errors as Schmidt "consider" parameters.

Why consider parameters: a wheel a little larger than nominal is a constant error, not
white noise. Its effect on the pose grows with the distance driven (the heading) and
with its square (the position), faster than any white process noise can describe, so a
filter that took it for white noise would grow overconfident on a long run without a
fix. Carrying the cross-covariance `C` between the pose and the two scale errors (whose
own covariance stays at its prior: they are considered, not estimated) makes the pose
covariance grow the way the real error does, at the cost of a 3x2 block.

Plain Python floats on purpose: with 3x3 matrices numpy's per-call overhead (a few
microseconds per product) costs more than the arithmetic (docs/PERFORMANCE.md). A
symmetric 3x3 matrix is the tuple of its upper triangle `(xx, xy, xt, yy, yt, tt)`
(`phalanx.core.fixes.Cov6`); `C` is row-major `(x_l, x_r, y_l, y_r, t_l, t_r)`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

from phalanx.core.fixes import Cov6

Mat = list[list[float]]
ZERO_C = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


class Belief(NamedTuple):
    """The filter's state: the pose (m, rad), its covariance `p` and its cross-covariance
    `c` with the two wheels' scale errors.
    """

    x: float
    y: float
    th: float
    p: Cov6
    c: tuple[float, float, float, float, float, float] = ZERO_C


@dataclass(frozen=True, slots=True)
class ProcessNoise:
    """Odometry's error model as the filter sees it (SI units).

    `track_m`: wheel separation; `scale_var`: prior variance of each wheel's scale error;
    `walk_var_per_m`: variance of a wheel's travel per metre travelled (random walk, and
    slip as a variance); `floor_var_m2ps`, `floor_var_rad2ps`: white noise per second
    on x, y and on the heading, so a robot standing still keeps a little uncertainty.
    """

    track_m: float
    scale_var: float
    walk_var_per_m: float
    slip_var_per_m3: float
    floor_var_m2ps: float
    floor_var_rad2ps: float


def wrap(angle_rad: float) -> float:
    """The angle in [-pi, pi)."""
    return (angle_rad + math.pi) % (2.0 * math.pi) - math.pi


def predict(b: Belief, ds_m: float, dth_rad: float, dt_s: float, q: ProcessNoise) -> Belief:
    """The belief after the robot drove the arc (`ds_m`, `dth_rad`) its odometry measured,
    over `dt_s`.
    """
    half = 0.5 * dth_rad
    chord = ds_m * (math.sin(half) / half if abs(half) > 1e-9 else 1.0 - half * half / 6.0)
    mid = b.th + half
    cm, sm = math.cos(mid), math.sin(mid)
    dx, dy = chord * cm, chord * sm
    # F = I + [[0, 0, a], [0, 0, bb], [0, 0, 0]]
    a, bb = -dy, dx
    xx, xy, xt, yy, yt, tt = b.p
    pxx = xx + 2.0 * a * xt + a * a * tt
    pxy = xy + a * yt + bb * xt + a * bb * tt
    pxt = xt + a * tt
    pyy = yy + 2.0 * bb * yt + bb * bb * tt
    pyt = yt + bb * tt
    # G = d(pose)/d(ds, dth); the wheels' travel and what their errors do to (ds, dth)
    g00, g01, g10, g11 = cm, -0.5 * dy, sm, 0.5 * dx
    w = q.track_m
    dl, dr = ds_m - 0.5 * w * dth_rad, ds_m + 0.5 * w * dth_rad
    # d(ds, dth)/d(eps_l, eps_r) = [[-dl/2, -dr/2], [dl/w, -dr/w]]; ge = G E (3x2)
    e00, e01, e10, e11 = -0.5 * dl, -0.5 * dr, dl / w, -dr / w
    ge = (
        g00 * e00 + g01 * e10,
        g00 * e01 + g01 * e11,
        g10 * e00 + g11 * e10,
        g10 * e01 + g11 * e11,
        e10,
        e11,
    )
    # F C, then P' = F P F^T + (F C Ge^T + its transpose) + s2 Ge Ge^T + G Qu G^T + floor
    c0, c1, c2, c3, c4, c5 = b.c
    f0, f1, f2, f3, f4, f5 = c0 + a * c4, c1 + a * c5, c2 + bb * c4, c3 + bb * c5, c4, c5
    h0, h1, h2, h3, h4, h5 = ge
    s2 = q.scale_var
    # white wheel noise, mapped through d(ds, dth)/d(dl, dr) = [[1/2, 1/2], [-1/w, 1/w]]
    vl = q.walk_var_per_m * abs(dl) + q.slip_var_per_m3 * abs(dl) ** 3
    vr = q.walk_var_per_m * abs(dr) + q.slip_var_per_m3 * abs(dr) ** 3
    qss, qst, qtt = 0.25 * (vl + vr), 0.5 * (vr - vl) / w, (vl + vr) / (w * w)
    u00, u01 = g00 * qss + g01 * qst, g00 * qst + g01 * qtt  # rows of G Qu
    u10, u11 = g10 * qss + g11 * qst, g10 * qst + g11 * qtt
    fm, fr = q.floor_var_m2ps * dt_s, q.floor_var_rad2ps * dt_s
    p = (
        pxx + 2.0 * (f0 * h0 + f1 * h1) + s2 * (h0 * h0 + h1 * h1) + u00 * g00 + u01 * g01 + fm,
        pxy + f0 * h2 + f1 * h3 + f2 * h0 + f3 * h1 + s2 * (h0 * h2 + h1 * h3)
        + u00 * g10 + u01 * g11,
        pxt + f0 * h4 + f1 * h5 + f4 * h0 + f5 * h1 + s2 * (h0 * h4 + h1 * h5) + u01,
        pyy + 2.0 * (f2 * h2 + f3 * h3) + s2 * (h2 * h2 + h3 * h3) + u10 * g10 + u11 * g11 + fm,
        pyt + f2 * h4 + f3 * h5 + f4 * h2 + f5 * h3 + s2 * (h2 * h4 + h3 * h5) + u11,
        tt + 2.0 * (f4 * h4 + f5 * h5) + s2 * (h4 * h4 + h5 * h5) + qtt + fr,
    )  # fmt: skip
    c_new = (f0 + s2 * h0, f1 + s2 * h1, f2 + s2 * h2, f3 + s2 * h3, f4 + s2 * h4, f5 + s2 * h5)
    return Belief(b.x + dx, b.y + dy, wrap(b.th + dth_rad), p, c_new)


def sym3_inverse(s: Cov6) -> Cov6 | None:
    """The inverse of a symmetric 3x3 matrix (upper triangles), None if singular."""
    a, b, c, d, e, f = s
    i_a, i_b, i_c = d * f - e * e, c * e - b * f, b * e - c * d
    det = a * i_a + b * i_b + c * i_c
    if not det > 1e-300:
        return None
    k = 1.0 / det
    return (
        i_a * k,
        i_b * k,
        i_c * k,
        (a * f - c * c) * k,
        (b * c - a * e) * k,
        (a * d - b * b) * k,
    )


def full(s: Cov6) -> Mat:
    """A symmetric 3x3 matrix from its upper triangle."""
    xx, xy, xt, yy, yt, tt = s
    return [[xx, xy, xt], [xy, yy, yt], [xt, yt, tt]]


def update_pose(b: Belief, z: tuple[float, float, float], r: Cov6, gate: float) -> Belief | None:
    """The belief corrected by a direct measurement of the pose `z` (x, y, theta) with
    covariance `r`; None when the measurement fails the gate (Mahalanobis distance
    squared over `gate`) or is degenerate; H = I, written out (the hot path).
    """
    nu0, nu1, nu2 = z[0] - b.x, z[1] - b.y, wrap(z[2] - b.th)
    pxx, pxy, pxt, pyy, pyt, ptt = b.p
    si = sym3_inverse((pxx + r[0], pxy + r[1], pxt + r[2], pyy + r[3], pyt + r[4], ptt + r[5]))
    if si is None:
        return None
    a, bb, c, d, e, f = si
    w0, w1, w2 = (
        a * nu0 + bb * nu1 + c * nu2,
        bb * nu0 + d * nu1 + e * nu2,
        c * nu0 + e * nu1 + f * nu2,
    )
    if nu0 * w0 + nu1 * w1 + nu2 * w2 > gate:
        return None
    # K = P S^-1 (rows of P times the symmetric S^-1)
    k00, k01, k02 = (
        pxx * a + pxy * bb + pxt * c,
        pxx * bb + pxy * d + pxt * e,
        pxx * c + pxy * e + pxt * f,
    )
    k10, k11, k12 = (
        pxy * a + pyy * bb + pyt * c,
        pxy * bb + pyy * d + pyt * e,
        pxy * c + pyy * e + pyt * f,
    )
    k20, k21, k22 = (
        pxt * a + pyt * bb + ptt * c,
        pxt * bb + pyt * d + ptt * e,
        pxt * c + pyt * e + ptt * f,
    )
    # x += P w; P' = P - K P; C' = C - K C
    p = (
        pxx - (k00 * pxx + k01 * pxy + k02 * pxt),
        pxy - (k00 * pxy + k01 * pyy + k02 * pyt),
        pxt - (k00 * pxt + k01 * pyt + k02 * ptt),
        pyy - (k10 * pxy + k11 * pyy + k12 * pyt),
        pyt - (k10 * pxt + k11 * pyt + k12 * ptt),
        ptt - (k20 * pxt + k21 * pyt + k22 * ptt),
    )
    c0, c1, c2, c3, c4, c5 = b.c
    c_new = (
        c0 - (k00 * c0 + k01 * c2 + k02 * c4),
        c1 - (k00 * c1 + k01 * c3 + k02 * c5),
        c2 - (k10 * c0 + k11 * c2 + k12 * c4),
        c3 - (k10 * c1 + k11 * c3 + k12 * c5),
        c4 - (k20 * c0 + k21 * c2 + k22 * c4),
        c5 - (k20 * c1 + k21 * c3 + k22 * c5),
    )
    return Belief(
        b.x + pxx * w0 + pxy * w1 + pxt * w2,
        b.y + pxy * w0 + pyy * w1 + pyt * w2,
        wrap(b.th + pxt * w0 + pyt * w1 + ptt * w2),
        p,
        c_new,
    )


def update(
    b: Belief, h: Mat, nu: list[float] | tuple[float, ...], r: Mat, gate: float
) -> Belief | None:
    """The belief corrected by a measurement with Jacobian `h` (m x 3), innovation `nu`
    (angles already wrapped) and noise covariance `r` (m x m); None when it fails the gate.
    """
    return _update(b, h, nu, r, gate)


def _update(
    b: Belief, h: Mat, nu: list[float] | tuple[float, ...], r: Mat, gate: float
) -> Belief | None:
    p, n = full(b.p), len(nu)
    ph = [[sum(p[i][k] * h[j][k] for k in range(3)) for j in range(n)] for i in range(3)]  # P H^T
    s = [[sum(h[i][k] * ph[k][j] for k in range(3)) + r[i][j] for j in range(n)] for i in range(n)]
    s_inv = _inverse(s)
    if s_inv is None:
        return None
    w = [sum(s_inv[i][j] * nu[j] for j in range(n)) for i in range(n)]
    if sum(nu[i] * w[i] for i in range(n)) > gate:
        return None
    gain = [[sum(ph[i][k] * s_inv[k][j] for k in range(n)) for j in range(n)] for i in range(3)]
    dx = [sum(gain[i][j] * nu[j] for j in range(n)) for i in range(3)]
    # P' = P - K (H P), C' = C - K (H C)
    hp = [[ph[k][i] for k in range(3)] for i in range(n)]  # H P = (P H^T)^T
    c = b.c
    hc = [[sum(h[i][k] * c[2 * k + j] for k in range(3)) for j in range(2)] for i in range(n)]

    def p_new(i: int, j: int) -> float:
        return p[i][j] - sum(gain[i][k] * hp[k][j] for k in range(n))

    p_out = (p_new(0, 0), p_new(0, 1), p_new(0, 2), p_new(1, 1), p_new(1, 2), p_new(2, 2))
    c_out = tuple(
        c[2 * i + j] - sum(gain[i][k] * hc[k][j] for k in range(n))
        for i in range(3)
        for j in range(2)
    )
    return Belief(
        b.x + dx[0],
        b.y + dx[1],
        wrap(b.th + dx[2]),
        p_out,
        c_out,  # type: ignore[arg-type]
    )


def _inverse(s: Mat) -> Mat | None:
    n = len(s)
    if n == 3:
        inv = sym3_inverse((s[0][0], s[0][1], s[0][2], s[1][1], s[1][2], s[2][2]))
        return None if inv is None else full(inv)
    if n == 2:
        det = s[0][0] * s[1][1] - s[0][1] * s[1][0]
        if not det > 1e-300:
            return None
        return [[s[1][1] / det, -s[0][1] / det], [-s[1][0] / det, s[0][0] / det]]
    if n == 1 and s[0][0] > 1e-300:
        return [[1.0 / s[0][0]]]
    return None
