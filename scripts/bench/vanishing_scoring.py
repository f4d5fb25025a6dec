"""Detected vertical segments against a synthetic scene's true edges.

A helper module, not a script: the scoring of ``bench/vanishing.py``'s
``synthetic`` section, shared with ``diagnose/second_pass.py`` (which traces
that section's misses), and the ``--set PATH=VALUE`` overrides of
``VanishingOptions`` both take. They import it after putting
``scripts/bench/`` on the path (``scripts/README.md``).
"""

from __future__ import annotations

import ast
import dataclasses

import numpy as np

from obliq_colmap.lines import bilinear
from obliq_colmap.vanishing import VanishingOptions


def on_line(true_seg, det, tol=1.0):
    """(M, N) overlap lengths along true segments of detections within tol px."""
    p0, p1 = true_seg[:, 0], true_seg[:, 1]
    d = p1 - p0
    L = np.linalg.norm(d, axis=1)
    t = d / np.maximum(L, 1e-9)[:, None]
    n = np.stack([-t[:, 1], t[:, 0]], axis=1)
    q = det  # (N, 2, 2)
    dist = np.abs(
        np.einsum("nkd,md->mnk", q, n) - np.sum(p0 * n, axis=1)[:, None, None]
    )
    s = np.einsum("nkd,md->mnk", q, t) - np.sum(p0 * t, axis=1)[:, None, None]
    lo = np.maximum(np.minimum(s[..., 0], s[..., 1]), 0)
    hi = np.minimum(np.maximum(s[..., 0], s[..., 1]), L[:, None])
    close = dist.max(axis=2) <= tol
    return np.where(close, np.maximum(hi - lo, 0), 0.0), lo, hi, close


def union_coverage(lo, hi, close, L):
    """Fraction of each true segment covered by the union of close detections."""
    cov = np.zeros(len(L))
    for m in range(len(L)):
        idx = np.flatnonzero(close[m] & (hi[m] > lo[m]))
        if len(idx) == 0:
            continue
        iv = sorted(zip(lo[m, idx], hi[m, idx], strict=True))
        total, cur_lo, cur_hi = 0.0, *iv[0]
        for a, b in iv[1:]:
            if a > cur_hi:
                total += cur_hi - cur_lo
                cur_lo, cur_hi = a, b
            else:
                cur_hi = max(cur_hi, b)
        cov[m] = (total + cur_hi - cur_lo) / max(L[m], 1e-9)
    return cov


def edge_contrast(img: np.ndarray, segs: np.ndarray, offset_px: float = 2.0):
    """(M,) median |I(+offset) - I(-offset)| across segments (9 samples each)."""
    d = segs[:, 1] - segs[:, 0]
    L = np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    n = np.stack([-d[:, 1], d[:, 0]], axis=1) / L
    f = np.linspace(0.1, 0.9, 9)
    P = segs[:, None, 0] + f[None, :, None] * d[:, None]
    gray = img.astype(float)
    a = bilinear(gray, (P + offset_px * n[:, None]).reshape(-1, 2)).reshape(-1, 9)
    b = bilinear(gray, (P - offset_px * n[:, None]).reshape(-1, 2)).reshape(-1, 9)
    return np.median(np.abs(a - b), axis=1)


def step_contrast(gray, P, t_edge, n_edge, offset=2.0):
    """(K,) |I(+offset) - I(-offset)| across an edge at points P (K, 2).

    Mean of 3 samples along it (-1, 0, +1 px); t_edge, n_edge (K, 2) unit
    tangent and normal at each point; gray (H, W) float image.
    """
    acc = np.zeros(len(P))
    for a in (-1.0, 0.0, 1.0):
        Q = P + a * t_edge
        acc += np.abs(
            bilinear(gray, Q + offset * n_edge) - bilinear(gray, Q - offset * n_edge)
        )
    return acc / 3


def vertical_in_3d(det, camera, pose, depth, max_angle_deg=3.0, offset_px=1.5):
    """(N,) bool: a detection back-projects onto a vertical 3D line.

    Points at 10..90% of each detection, moved ``offset_px`` to either side,
    are lifted to 3D with the true depth buffer (local frame); a detection
    counts when, on either side, the 3D points lie on one line (all within
    0.1 m + 2 pixel footprints of the chord) within ``max_angle_deg`` of the
    vertical. Covers texture edges (windows, shop fronts, panels) and
    structures (tree trunks) that the list of true 3D edges does not hold;
    lines on the ground or on roofs fail.
    """
    if len(det) == 0:
        return np.zeros(0, bool)
    H, W = depth.shape
    d = det[:, 1] - det[:, 0]
    L = np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-9)
    n = np.stack([-d[:, 1], d[:, 0]], axis=1) / L
    f = np.linspace(0.1, 0.9, 9)
    Kinv = np.linalg.inv(camera.K)
    R, t = pose.rotation, pose.translation
    ok = np.zeros(len(det), bool)
    for side in (1.0, -1.0):
        P = (
            det[:, None, 0]
            + f[None, :, None] * d[:, None]
            + side * offset_px * n[:, None]
        )
        # Detections are undistorted; the depth buffer is on the image grid.
        Pd = P
        if camera.has_distortion:
            Pd = camera.distort_pixels(P.reshape(-1, 2)).reshape(P.shape)
        col = np.clip(np.floor(Pd[..., 0]).astype(int), 0, W - 1)
        row = np.clip(np.floor(Pd[..., 1]).astype(int), 0, H - 1)
        z = depth[row, col].astype(float)  # (N, 9)
        ray = np.concatenate([P, np.ones(P.shape[:2] + (1,))], axis=2) @ Kinv.T
        Xc = ray * z[..., None]
        X = (Xc - t) @ R  # world (local) = R^T (Xc - t)
        finite = np.isfinite(X).all(axis=(1, 2))
        X = np.where(np.isfinite(X), X, 0.0)
        chord = X[:, -1] - X[:, 0]
        lc = np.maximum(np.linalg.norm(chord, axis=1), 1e-9)
        u = chord / lc[:, None]
        rel = X - X[:, :1]
        off = np.linalg.norm(
            rel - np.sum(rel * u[:, None], axis=2)[..., None] * u[:, None], axis=2
        )
        tol = 0.1 + 2.0 * z.max(axis=1) / camera.K[0, 0]
        straight = off.max(axis=1) <= tol
        vertical = np.abs(u[:, 2]) >= np.cos(np.radians(max_angle_deg))
        ok |= finite & straight & vertical
    return ok


def with_overrides(options: VanishingOptions, items: list[str]) -> VanishingOptions:
    """``options`` with ``PATH=VALUE`` overrides (``second_pass.weak_high=4``)."""
    for item in items:
        path, _, text = item.partition("=")
        keys = path.strip().split(".")
        value = ast.literal_eval(text.strip())

        def replace(obj, keys, value=value, path=path):
            if not dataclasses.is_dataclass(obj) or keys[0] not in {
                f.name for f in dataclasses.fields(obj)
            }:
                raise SystemExit(f"--set {path}: no option {keys[0]!r}")
            if len(keys) == 1:
                return dataclasses.replace(obj, **{keys[0]: value})
            inner = replace(getattr(obj, keys[0]), keys[1:])
            return dataclasses.replace(obj, **{keys[0]: inner})

        options = replace(options, keys)
    return options
