"""Variance components per observation group, and the covariance they give.

The bundle weights each group of observations (map corners, segment
directions, facade rows, tie points, VPs, pose and principal-point priors)
by a stated sd. At the optimum each group's weighted squared residuals over
its share of the redundancy say how far that sd is off: the group's
variance component (Förstner's estimate,
``v_g = r_g^T W_g r_g / (n_g - u_g - tr(Q N_g))`` with ``u_g`` the unknowns
only the group observes and ``N_g`` its normal matrix on the camera block,
those unknowns eliminated). One factor for all groups (the pooled variance
factor) lets the noisiest group (tie points with heavy tails) inflate the
sd of what the others determine, and a group noisier than stated makes the
rest optimistic.

The solution stays the one the stated weights gave. Its covariance with the
groups' noise at ``v_g`` times the stated is the sandwich
``Q (sum_g v_g N_g) Q`` over the groups, ``Q`` the cofactor matrix of the
gauge-constrained solution (``Q = (sum_g N_g)^+``); with every ``v_g = v``
it is the pooled ``v Q`` (``Q N Q = Q`` for the constrained inverse).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["Group", "component_factors", "sandwich_covariance", "shared_meat"]


@dataclass
class Group:
    """One group of observations at the optimum."""

    name: str
    #: (n, n) its normal matrix on the camera block (``J^T W J`` with its
    #: robust weights; its own unknowns eliminated).
    normal: np.ndarray
    #: ``r^T W r`` with the robust weights, at the optimum of the unknowns
    #: ``private`` counts (``covariance.private_refit``).
    wss: float
    #: Its rows (observations), prior rows on its own unknowns included.
    rows: int
    #: What the unknowns only it observes (tie points, facade heights and
    #: offsets) take of its rows: their number where its rows determine
    #: them, less where a prior does (``covariance.private_share``).
    private: float = 0.0
    #: (n, n) what errors its rows share add between the cofactors
    #: (``covariance.corner_offset_meat``: the map corners' own error), in
    #: the stated units, not scaled by the group's factor; None: none.
    shared: np.ndarray | None = None

    def redundancy(self, Q: np.ndarray) -> float:
        """Its share of the redundancy: rows less its own unknowns and its
        part of the camera block's, ``tr(Q N_g)``."""
        return self.rows - self.private - float(np.sum(Q * self.normal.T))


def component_factors(
    groups: list[Group], Q: np.ndarray, min_redundancy: float
) -> dict[str, tuple[float, float]]:
    """Per group name: (variance component, redundancy). A group with less
    than ``min_redundancy`` (a handful of prior rows) keeps its stated sd
    (factor 1): its estimate would be noise."""
    out = {}
    for g in groups:
        red = g.redundancy(Q)
        factor = g.wss / red if red >= min_redundancy and g.wss > 0 else 1.0
        out[g.name] = (float(factor), float(red))
    return out


def shared_meat(groups: list[Group]) -> np.ndarray | None:
    """(n, n) the sum of the groups' ``shared`` terms; None without any."""
    terms = [g.shared for g in groups if g.shared is not None]
    return sum(terms[1:], terms[0]) if terms else None


def sandwich_covariance(
    groups: list[Group], Q: np.ndarray, factors: dict[str, tuple[float, float]]
) -> np.ndarray:
    """(n, n) ``Q (sum_g v_g N_g + S) Q``: the camera block's covariance with
    each group's noise at its factor ``v_g`` (``factors``' first entries)
    times its stated variance, and the errors shared by rows ``S``
    (:func:`shared_meat`)."""
    M = sum(factors[g.name][0] * g.normal for g in groups)
    shared = shared_meat(groups)
    if shared is not None:
        M = M + shared
    C = Q @ M @ Q
    return 0.5 * (C + C.T)
