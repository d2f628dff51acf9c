"""A pose estimate's uncertainty as the map shows it: the ellipse its position covariance
draws (2 sigma: 86 % of the probability in 2D), beside ground truth.

Entities: `robots/<id>/covariance` (the ellipse round the published pose), and, where
the truth is known (a batch run's recording), `robots/<id>/estimate/error_m` and
`robots/<id>/estimate/std_m` (the larger axis's sigma).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
import numpy.typing as npt

FloatArray = npt.NDArray[np.float64]
ELLIPSE_SIGMA = 2.0
ELLIPSE_POINTS = 24
ELLIPSE_RADIUS_M = 0.004
_ANGLES = np.linspace(0.0, 2.0 * math.pi, ELLIPSE_POINTS + 1)
_CIRCLE = np.column_stack([np.cos(_ANGLES), np.sin(_ANGLES)])


def ellipse(x_m: float, y_m: float, cov: Sequence[float]) -> list[tuple[float, float]]:
    """The 2-sigma ellipse of the position block of `cov` (xx, xy, xt, yy, yt, tt) round
    (x, y), as a closed strip; empty for a covariance that is not one.
    """
    if len(cov) != 6:
        return []
    block = np.array([[cov[0], cov[1]], [cov[1], cov[3]]])
    values, vectors = np.linalg.eigh(block)
    if not np.all(np.isfinite(values)) or values.min() < -1e-12:
        return []
    axes = vectors * (ELLIPSE_SIGMA * np.sqrt(np.clip(values, 0.0, None)))
    points = _CIRCLE @ axes.T + (x_m, y_m)
    return [(float(px), float(py)) for px, py in points]


def position_std_m(cov: Sequence[float]) -> float:
    """The larger sigma of the position block (m); NaN without a covariance."""
    if len(cov) != 6:
        return math.nan
    xx, xy, yy = cov[0], cov[1], cov[3]
    return math.sqrt(max(0.0, 0.5 * (xx + yy) + math.sqrt(0.25 * (xx - yy) ** 2 + xy * xy)))


def send_ellipses(
    rec: Any, rr: Any, path: str, index: list[Any], strips: Sequence[list[tuple[float, float]]]
) -> None:
    """One ellipse (or none) per indexed step, as one column send."""
    flat = [s for s in strips if s]
    columns = rr.LineStrips2D.columns(
        strips=flat, radii=np.full(len(flat), ELLIPSE_RADIUS_M)
    ).partition([1 if s else 0 for s in strips])
    rec.send_columns(path, indexes=index, columns=columns)
