#!/usr/bin/env python
"""How well can stage 1's edges fix the vertical VP at all? The VP fitted
only to the second-pass chains that lie on the projected TRUE vertical
building edges (issue 25, class (a): "the information is not there" or
"the method cannot").

For each named image of a scene in the external format (``images/``,
``gt/``, ``gt_buildings.json``), with the TRUE camera (lens distortion
removed as stage 1 removes it): the second pass through the true VP; the
chains whose midpoint lies within 1.5 px of a projected true wall corner
(footprint vertex from its base to the eave height); the VP refined
(``refine_vp``, the second pass's maximum-likelihood fit) on those chains
and, for comparison, on all chains, both started AT the truth. A perfect
classifier of building edges could do no better than the first figure with
these edges; the second says where the clutter pulls the fit. Last, where
those chains' own lines (each fitted to its edge points alone) lie across
the true corner at their upper and lower ends (median, px; + = away from
the VP's column): a lean of the whole edge that no choice of chains removes.

Run (from the repository root)::

    python scripts/diagnose/vp_edge_oracle.py SCENE IMAGE_NAME [IMAGE_NAME ...]

SCENE: the external format or an ``obliq-colmap synth`` scene (its
``gt_buildings.json`` lists ground and eave corners; the wall corners are
those pairs, :func:`wall_corners`).
"""

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from obliq_colmap.geometry import Camera
from obliq_colmap.lines import fit_lines, gradients
from obliq_colmap.vanishing import VanishingOptions
from obliq_colmap.vanishing.pencil import canonical_sign, normaliser, refine_vp
from obliq_colmap.vanishing.second_pass import run_second_pass


def true_edges(gt_buildings: Path) -> np.ndarray:
    """(N, 2, 3) every footprint vertex's wall corner, base to eave."""
    data = json.loads(gt_buildings.read_text())
    edges = []
    for b in data["buildings"]:
        if b.get("kind") != "building":
            continue
        for ring, zs in zip(b["footprint"], b["base_z"], strict=True):
            for (x, y), z in zip(ring, zs, strict=True):
                edges.append(((x, y, z), (x, y, b["eave_z"])))
    return np.array(edges, float)


def wall_corners(path: Path) -> np.ndarray:
    """(N, 2, 3) wall corners base to eave: the external format's
    (:func:`true_edges`) or ``obliq-colmap synth``'s (ground and
    eave corners of each building, paired by position)."""
    data = json.loads(path.read_text())
    if "corner_kind" not in data:
        return true_edges(path)
    X = np.asarray(data["corners"], float)
    kind = np.asarray(data["corner_kind"])
    bld = np.asarray(data["corner_building"])
    edges = []
    for b in np.unique(bld):
        g = X[(bld == b) & (kind == "ground")]
        e = X[(bld == b) & (kind == "eave")]
        if not len(g) or not len(e):
            continue
        d = np.linalg.norm(g[:, None, :2] - e[None, :, :2], axis=2)
        j = d.argmin(1)
        near = d[np.arange(len(g)), j] < 0.05
        edges += [(a, c) for a, c in zip(g[near], e[j[near]], strict=True)]
    return np.array(edges, float)


def distance_to_segments(p: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """(P,) distance of points (P, 2) to the nearest of segments (N, 2, 2)."""
    a, ab = ends[:, 0], ends[:, 1] - ends[:, 0]
    t = ((p[:, None] - a[None]) * ab[None]).sum(2) / (ab**2).sum(1)[None]
    foot = a[None] + np.clip(t, 0.0, 1.0)[..., None] * ab[None]
    return np.linalg.norm(p[:, None] - foot, axis=2).min(1)


def end_offsets(
    ends: np.ndarray, own: np.ndarray, corners: np.ndarray, vp: np.ndarray
) -> np.ndarray:
    """(C, 2) signed offsets (px) of each chain's upper and lower end from
    the nearest true corner line, measured on the chain's own line.

    ends: (C, 2, 2) chain ends; own: (C, 3) the chains' own lines (pixels,
    unit normal); corners: (N, 2, 2) projected true corners; vp: (2,) the
    true VP. + = away from the vertical through the VP; upper = the end
    farther from the VP.
    """
    a, ab = corners[:, 0], corners[:, 1] - corners[:, 0]
    u = ab / np.linalg.norm(ab, axis=1, keepdims=True)
    dist = np.einsum("cej,cj->ce", ends, own[:, :2]) + own[:, 2:]
    feet = ends - dist[..., None] * own[:, None, :2]
    mid = feet.mean(axis=1)
    k = np.argmin(np.abs(_cross(mid[:, None] - a[None], u[None])), axis=1)
    sgn = np.sign(mid[:, 0] - vp[0]) * np.sign(u[k, 1])
    off = _cross(feet - a[k][:, None], u[k][:, None]) * sgn[:, None]
    upper = np.linalg.norm(feet[:, 0] - vp, axis=1) > np.linalg.norm(
        feet[:, 1] - vp, axis=1
    )
    return np.where(upper[:, None], off, off[:, ::-1])


def _cross(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """z of the 2D cross product, broadcast over leading axes."""
    return p[..., 0] * q[..., 1] - p[..., 1] * q[..., 0]


def angle_deg(K: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    """Angle between the directions of homogeneous VPs a, b through K."""
    da, db = np.linalg.solve(K, a), np.linalg.solve(K, b)
    c = abs(da @ db) / np.linalg.norm(da) / np.linalg.norm(db)
    return float(np.degrees(np.arccos(min(1.0, c))))


def one_image(scene: Path, gt, image, edges: np.ndarray, opts) -> str:
    gc = gt.cameras[image.camera_id]
    cam = Camera(gc.model.name, gc.width, gc.height, np.asarray(gc.params))
    img = cv2.imread(str(scene / "images" / image.name), cv2.IMREAD_GRAYSCALE)
    pose = image.cam_from_world()
    R, t, K = pose.rotation.matrix(), pose.translation, cam.K
    vt = canonical_sign(K @ R[:, 2] / np.linalg.norm(K @ R[:, 2]))
    Xc = edges.reshape(-1, 3) @ R.T + t
    px = Xc @ K.T
    px = (px[:, :2] / px[:, 2:]).reshape(-1, 2, 2)  # undistorted pixels
    H, W = img.shape
    inside = np.all(
        (px[..., 0] > 0) & (px[..., 0] < W) & (px[..., 1] > 0) & (px[..., 1] < H),
        axis=1,
    ) & np.all(Xc.reshape(-1, 2, 3)[..., 2] > 0, axis=1)
    T, _ = normaliser(W, H)
    grads = gradients(img, opts.second_pass.sigma_px)
    sp = run_second_pass(img, vt, opts.second_pass, cam, T, grads)
    seg = sp.segments.endpoints
    on = distance_to_segments(seg.mean(axis=1), px[inside]) < 1.5
    v0 = T @ vt / np.linalg.norm(T @ vt)
    Ti = np.linalg.inv(T)
    v_on = refine_vp(sp.scatter[on], v0)[0]
    v_all = refine_vp(sp.scatter, v0)[0]
    length = np.linalg.norm(seg[on, 1] - seg[on, 0], axis=1)
    own = fit_lines(sp.scatter[on])[0] @ T  # each chain's own line, pixels
    own /= np.linalg.norm(own[:, :2], axis=1, keepdims=True)
    upper, lower = np.median(end_offsets(seg[on], own, px[inside], vt[:2] / vt[2]), 0)
    return (
        f"{image.name}: {on.sum()} of {len(on)} chains on true edges (median"
        f" {np.median(length):.0f} px); VP from them"
        f" {angle_deg(K, Ti @ v_on, vt):.2f} deg, from all chains"
        f" {angle_deg(K, Ti @ v_all, vt):.2f} deg (both started at the truth);"
        f" own lines off the corner at their upper / lower ends"
        f" {upper:+.2f} / {lower:+.2f} px"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene", type=Path)
    ap.add_argument("names", nargs="+")
    args = ap.parse_args()
    gt = pycolmap.Reconstruction(str(args.scene / "gt"))
    by_name = {im.name: im for im in gt.images.values()}
    edges = wall_corners(args.scene / "gt_buildings.json")
    opts = VanishingOptions()
    for name in args.names:
        print(one_image(args.scene, gt, by_name[name], edges, opts), flush=True)


if __name__ == "__main__":
    main()
