"""Homogeneous helpers and the pencil maths: lines through one vanishing point.

Conditioning (:func:`normaliser`), the closed-form best line through a VP of
each group of points (:func:`pencil_fit`, costs for many VPs at once), the
maximum-likelihood VP (:func:`refine_vp`, Newton on the sphere), the
midpoint distance RANSAC scores with, and the vertical direction of a VP.
"""

from __future__ import annotations

import math

import numpy as np

from obliq_colmap.geometry import tangent_basis
from obliq_colmap.lines import scatter_matrices


def nominal_K(W: int, H: int) -> np.ndarray:
    """The nominal camera (focal max(W, H), centred) when K is unknown."""
    return np.array([[max(W, H), 0, W / 2], [0, max(W, H), H / 2], [0, 0, 1.0]])


def normaliser(width: int, height: int) -> tuple[np.ndarray, float]:
    """T mapping pixels to centred coordinates scaled by half the longer side."""
    s = max(width, height) / 2.0
    T = np.array([[1 / s, 0, -width / 2 / s], [0, 1 / s, -height / 2 / s], [0, 0, 1.0]])
    return T, s


def canonical_sign(v: np.ndarray) -> np.ndarray:
    """Flip homogeneous vectors (..., 3) so that w >= 0 (y >= 0 at infinity)."""
    w = v[..., 2]
    key = np.where(np.abs(w) > 1e-12 * np.linalg.norm(v, axis=-1), w, v[..., 1])
    return v * np.where(key < 0, -1.0, 1.0)[..., None]


def _pencil_forms(S: np.ndarray, U: np.ndarray) -> tuple[np.ndarray, ...]:
    """The 2x2 forms of :func:`pencil_fit` for (P, 3, 2) bases U.

    ``A_c = U^T S_c U`` (its 3 distinct entries, from the 9 entries of each S
    in one matrix product over all (P, G)) and ``B = U[:2]^T U[:2]`` (the form
    of ``a^2 + b^2`` of the line ``U x``).

    Returns
    -------
    a00, a01, a11 : (P, G) arrays; b00, b01, b11 : (P, 1) arrays.
    """
    P = len(U)
    u0, u1 = U[:, :, 0], U[:, :, 1]  # (P, 3)
    W = np.concatenate(
        [
            (u0[:, :, None] * u0[:, None, :]).reshape(P, 1, 9),
            (u0[:, :, None] * u1[:, None, :]).reshape(P, 1, 9),
            (u1[:, :, None] * u1[:, None, :]).reshape(P, 1, 9),
        ],
        axis=1,
    ).reshape(3 * P, 9)
    A = (W @ S.reshape(len(S), 9).T).reshape(P, 3, len(S))
    b00 = (u0[:, 0] * u0[:, 0] + u0[:, 1] * u0[:, 1])[:, None]
    b01 = (u0[:, 0] * u1[:, 0] + u0[:, 1] * u1[:, 1])[:, None]
    b11 = (u1[:, 0] * u1[:, 0] + u1[:, 1] * u1[:, 1])[:, None]
    return A[:, 0], A[:, 1], A[:, 2], b00, b01, b11


def _smallest_root(a00, a01, a11, b00, b01, b11) -> np.ndarray:
    """Smallest generalised eigenvalue of (A, B), clipped at 0 (broadcasting)."""
    qa = b00 * b11 - b01 * b01
    qb = a00 * b11 + a11 * b00 - 2 * a01 * b01
    qc = a00 * a11 - a01 * a01
    disc = np.sqrt(np.maximum(qb * qb - 4 * qa * qc, 0.0))
    # Smaller root of qa l^2 - qb l + qc = 0 in the cancellation-free form.
    return np.maximum(2 * qc / np.maximum(qb + disc, 1e-300), 0.0)


def pencil_costs_each(S: np.ndarray, V: np.ndarray) -> np.ndarray:
    """(P, G) cost of :func:`pencil_fit` of each group for each of (P, 3) V."""
    return _smallest_root(*_pencil_forms(S, tangent_basis(V)))


def _pencil_costs(S: np.ndarray, V: np.ndarray) -> np.ndarray:
    """Total cost ``sum_c lambda_c(v)`` of :func:`pencil_fit` for each of (P, 3) V."""
    return pencil_costs_each(S, V).sum(axis=1)


def pencil_cost(S: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(G,) the cost of :func:`pencil_fit` alone (no lines)."""
    return pencil_costs_each(S, np.asarray(v, float)[None])[0]


def pencil_fit(S: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Best line through v for each group of points, in closed form.

    Minimises ``l^T S_c l / (a^2 + b^2)`` over lines ``l = U x`` of the pencil
    through v (a 2x2 generalised eigenproblem; valid for v at infinity).

    Parameters
    ----------
    S : (G, 3, 3) scatter matrices (:func:`lines.scatter_matrices`).
    v : (3,) unit homogeneous point.

    Returns
    -------
    cost : (G,) sum of squared point-to-line distances of each group.
    lines : (G, 3) the lines, unit normal (a, b).
    """
    U = tangent_basis(v)  # (3, 2)
    a00, a01, a11, b00, b01, b11 = (f[0] for f in _pencil_forms(S, U[None]))
    lam = _smallest_root(a00, a01, a11, b00, b01, b11)
    # Eigenvector: a row of (A - lam B), rotated; use the larger row.
    m00, m01, m11 = a00 - lam * b00, a01 - lam * b01, a11 - lam * b11
    use0 = m01 * m01 + m00 * m00 >= m11 * m11 + m01 * m01
    x0 = np.where(use0, -m01, -m11)
    x1 = np.where(use0, m00, m01)
    lines = x0[:, None] * U[:, 0] + x1[:, None] * U[:, 1]
    nab = np.sqrt(lines[:, 0] ** 2 + lines[:, 1] ** 2)[:, None]
    lines = lines / np.where(nab > 0, nab, 1.0)
    return lam, lines


# Central-difference stencil of refine_vp, (9, 2): (a, b) for a, b in -1, 0, 1.
_STENCIL = np.array([(a, b) for a in (-1.0, 0.0, 1.0) for b in (-1.0, 0.0, 1.0)])


def refine_vp(
    S: np.ndarray, v0: np.ndarray, max_iterations: int = 20
) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Maximum-likelihood VP from groups of points whose lines pass through it.

    Minimises ``f(v) = sum_c min_{l through v} sum_i d(p_ci, l)^2`` (the line of
    each group eliminated in closed form, :func:`pencil_fit`) by Newton steps
    on the unit sphere (2 parameters; gradient and Hessian by central
    differences, the 9 stencil points evaluated in one vectorised call).

    Parameters
    ----------
    S : (G, 3, 3) scatter matrices in normalised coordinates.
    v0 : (3,) starting point, homogeneous.

    Returns
    -------
    v : (3,) unit homogeneous VP.
    covariance : (3, 3) covariance of v (rank 2): ``2 sigma^2 H^-1`` with
        sigma^2 = f / (n_points - G - 2), n_points the summed weights.
    cost : float, f(v).
    dof : int, degrees of freedom of the residual.
    """
    v = np.asarray(v0, float) / np.linalg.norm(v0)
    h = 1e-5
    grid = _STENCIL * h  # (9, 2)

    def stencil(v_):
        """(9, 3) points around v_ and v_'s tangent basis (3, 2)."""
        B = tangent_basis(v_)
        P = v_ + grid @ B.T
        return P / np.linalg.norm(P, axis=1, keepdims=True), B

    def derivatives(vals):
        """Value, gradient and Hessian (hxx, hxy, hyy) from the 9 stencil costs."""
        vals = vals.reshape(3, 3).tolist()
        g = ((vals[2][1] - vals[0][1]) / (2 * h), (vals[1][2] - vals[1][0]) / (2 * h))
        hxx = (vals[2][1] - 2 * vals[1][1] + vals[0][1]) / h**2
        hyy = (vals[1][2] - 2 * vals[1][1] + vals[1][0]) / h**2
        hxy = (vals[2][2] - vals[2][0] - vals[0][2] + vals[0][0]) / (4 * h * h)
        return vals[1][1], g, (hxx, hxy, hyy)

    ts = 0.5 ** np.arange(6)
    P9, B = stencil(v)
    f0, g, H = derivatives(_pencil_costs(S, P9))
    for _ in range(max_iterations):
        step = _newton_step(g, H)
        # Converged when the predicted decrease is below 1e-8 of the cost: the
        # remaining step is then ~sqrt(1e-8 x n_points) < 0.01 of the VP's
        # standard deviation (1e-12, rounding noise, took a third more steps).
        if -0.5 * (g[0] * step[0] + g[1] * step[1]) <= 1e-8 * max(f0, 1e-300) + 1e-300:
            break
        # Newton steps can be large far from the optimum: cap, then try a few
        # step lengths at once, together with the stencil around the full
        # step (usually taken), so that one call prices both.
        norm = math.hypot(step[0], step[1])
        if norm > 0.2:
            step = (step[0] * 0.2 / norm, step[1] * 0.2 / norm)
        P = v + np.outer(ts, step[0] * B[:, 0] + step[1] * B[:, 1])
        P /= np.linalg.norm(P, axis=1, keepdims=True)
        P9, B9 = stencil(P[0])
        vals = _pencil_costs(S, np.vstack([P, P9]))
        k = int(np.argmin(vals[: len(ts)]))
        if vals[k] > f0:
            break
        v = P[k]
        if k == 0:
            B, (f0, g, H) = B9, derivatives(vals[len(ts) :])
        else:
            P9, B = stencil(v)
            f0, g, H = derivatives(_pencil_costs(S, P9))
    H = np.array([[H[0], H[1]], [H[1], H[2]]])
    n_points = float(np.sum(S[:, 2, 2]))
    G = len(S)
    dof = int(round(n_points)) - G - 2
    sigma2 = f0 / dof if dof > 0 else np.inf
    try:
        cov_t = 2.0 * sigma2 * np.linalg.inv(H)
    except np.linalg.LinAlgError:
        cov_t = np.full((2, 2), np.inf)
    return v, B @ cov_t @ B.T, f0, dof


def _newton_step(g: tuple, H: tuple) -> tuple[float, float]:
    """-H^-1 g for a 2x2 symmetric H = (hxx, hxy, hyy), eigenvalues floored.

    Eigenvalues below 1e-9 of the largest are raised to it (a valley along
    the weakly determined direction: a bounded step instead of a wild one).
    Closed form of the 2x2 eigen-decomposition (numpy's costs more per call
    than the rest of a Newton iteration).
    """
    a, b, c = H
    m, r = 0.5 * (a + c), math.hypot(0.5 * (a - c), b)
    w1, w2 = m - r, m + r  # ascending
    theta = 0.5 * math.atan2(2 * b, a - c)  # (cos, sin): eigenvector of w2
    q2 = (math.cos(theta), math.sin(theta))
    q1 = (-q2[1], q2[0])
    floor = 1e-9 * max(w2, 1e-300) + 1e-300
    w1, w2 = max(w1, floor), max(w2, floor)
    p1 = (q1[0] * g[0] + q1[1] * g[1]) / w1
    p2 = (q2[0] * g[0] + q2[1] * g[1]) / w2
    return (-(q1[0] * p1 + q2[0] * p2), -(q1[1] * p1 + q2[1] * p2))


def endpoint_scatter(ends_n: np.ndarray) -> np.ndarray:
    """(G, 3, 3) scatter matrices of segments' two endpoints (normalised)."""
    G = len(ends_n)
    return scatter_matrices(ends_n.reshape(-1, 2), np.repeat(np.arange(G), 2), G)


def midpoint_distance(v: np.ndarray, mid: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Endpoint distances to the lines through midpoints and VPs.

    Parameters
    ----------
    v : (H, 3) homogeneous VPs; mid : (S, 2) midpoints; half : (S, 2) the
        vectors from the midpoints to endpoint 1. All normalised coordinates.

    Returns
    -------
    (H, S) distances, normalised units.
    """
    a, b, c = v[:, 0:1], v[:, 1:2], v[:, 2:3]
    # l = (mx, my, 1) x (a, b, c); its normal (lx, ly):
    lx = mid[None, :, 1] * c - b
    ly = a - mid[None, :, 0] * c
    num = np.abs(lx * half[None, :, 0] + ly * half[None, :, 1])
    return num / np.maximum(np.sqrt(lx * lx + ly * ly), 1e-300)


def vertical_direction(
    vp: np.ndarray, K: np.ndarray, down_cam: np.ndarray | None = None
) -> np.ndarray:
    """Unit vertical direction (3,) in the camera frame, pointing down the world.

    ``n = +-normalise(K^-1 vp)``, with ``n . down_cam > 0`` when a predicted down
    direction is known, otherwise ``n_y > 0``.
    """
    n = np.linalg.solve(K, np.asarray(vp, float))
    n /= np.linalg.norm(n)
    ref = n @ down_cam if down_cam is not None else n[1]
    return -n if ref < 0 else n


def direction_std_deg(vp: np.ndarray, cov: np.ndarray, K: np.ndarray) -> float:
    """1-sigma angle (deg) of normalise(K^-1 vp) from the covariance of vp."""
    if not np.isfinite(cov).all():
        return np.inf
    Kinv = np.linalg.inv(K)
    m = Kinv @ vp
    nm = np.linalg.norm(m)
    J = (np.eye(3) - np.outer(m, m) / nm**2) / nm @ Kinv
    c = J @ cov @ J.T
    tr = float(np.trace(c))
    return float(np.degrees(np.sqrt(tr))) if np.isfinite(tr) and tr >= 0 else np.inf


def grouped_jackknife_covariance(
    S: np.ndarray, v: np.ndarray, groups: np.ndarray | None = None, h: float = 1e-5
) -> np.ndarray:
    """(3, 3) covariance of the ML VP ``v`` of :func:`refine_vp` from the spread of
    its delete-a-group estimates (a jackknife over groups of point groups).

    ``v`` minimises ``f = sum_c f_c`` (``f_c`` the cost of group c,
    :func:`pencil_fit`). Deleting the groups of block b moves it by one Newton
    step, ``d_b = (H - H_b)^-1 g_b`` (``g_b``, ``H_b`` the gradient and Hessian
    of block b's cost at v, all from one vectorised stencil of per-group
    costs), and the covariance is ``(B - 1) / B sum_b (d_b - mean)(d_b -
    mean)^T``. Unlike ``2 sigma^2 H^-1`` it assumes nothing about the points
    of a group being independent: errors shared by the points of a chain (or
    by the chains of a block) show in the spread of the blocks' pulls.

    Parameters
    ----------
    S : (G, 3, 3) scatter matrices; v : (3,) unit VP (the minimum of f).
    groups : (G,) int block of each group (None: each group its own block).

    Returns
    -------
    (3, 3) covariance of v (rank 2); infinite with fewer than 3 blocks.
    """
    v = np.asarray(v, float) / np.linalg.norm(v)
    G = len(S)
    groups = np.arange(G) if groups is None else np.asarray(groups)
    B_ = tangent_basis(v)
    P = v + (_STENCIL * h) @ B_.T
    P /= np.linalg.norm(P, axis=1, keepdims=True)
    vals = pencil_costs_each(S, P)  # (9, G)
    nb = int(groups.max()) + 1 if G else 0
    if nb < 3:
        return np.full((3, 3), np.inf)
    vb = np.zeros((9, nb))
    np.add.at(vb.T, groups, vals.T)
    c = vb.reshape(3, 3, nb)
    g = np.stack([(c[2, 1] - c[0, 1]) / (2 * h), (c[1, 2] - c[1, 0]) / (2 * h)], -1)
    hxx = (c[2, 1] - 2 * c[1, 1] + c[0, 1]) / h**2
    hyy = (c[1, 2] - 2 * c[1, 1] + c[1, 0]) / h**2
    hxy = (c[2, 2] - c[2, 0] - c[0, 2] + c[0, 0]) / (4 * h * h)
    Hb = np.stack([np.stack([hxx, hxy], -1), np.stack([hxy, hyy], -1)], -2)  # (nb,2,2)
    Hm = Hb.sum(axis=0)[None] - Hb
    try:
        d = np.linalg.solve(Hm, g[..., None])[..., 0]  # (nb, 2)
    except np.linalg.LinAlgError:
        return np.full((3, 3), np.inf)
    d -= d.mean(axis=0)
    cov_t = (nb - 1) / nb * (d.T @ d)
    return B_ @ cov_t @ B_.T
