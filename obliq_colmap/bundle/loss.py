"""The robust losses of the bundle (Ceres' conventions)."""

from __future__ import annotations

import numpy as np

LOSSES = ("huber", "cauchy", "none")


def robust_loss(
    kind: str, scale: float, r2: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """rho(r^2) and rho'(r^2) of squared residuals ``r2`` (rho(s) = s for
    small s; ``scale`` in the residuals' unit); kind one of :data:`LOSSES`."""
    if kind == "none":
        return r2, np.ones_like(r2)
    b = scale * scale
    if kind == "huber":
        big = r2 > b
        sq = np.sqrt(np.where(big, r2, b))
        return np.where(big, 2.0 * scale * sq - b, r2), np.where(big, scale / sq, 1.0)
    # cauchy
    return b * np.log1p(r2 / b), 1.0 / (1.0 + r2 / b)
