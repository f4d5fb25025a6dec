"""Control points triangulated from their image observations in a COLMAP model.

A point is usable when at least ``min_observations`` of its observations lie
in images the model has registered and the rays meet in front of every
camera at a reasonable angle: then its position in the MODEL's frame is the
least-squares intersection (the midpoint of the undistorted rays), refined by
Gauss-Newton on the reprojection error through the models' own cameras
(``Camera.img_from_cam``: every COLMAP camera model, its distortion
included). Few points, a handful of images each: a loop over points is fine.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import pycolmap

from obliq_colmap.errors import InputError

from .model import ControlPoints

logger = logging.getLogger(__name__)

#: Rays meeting at less than this angle (deg) fix no position along them.
MIN_TRIANGULATION_ANGLE_DEG = 1.0


@dataclass
class ControlTriangulation:
    """Control points in a model's frame.

    names : (N,) list; xyz : (N, 3), NaN where not usable; n_observations :
    (N,) observations in registered images; usable : (N,) bool;
    image_ids : per point the (k,) image ids of its observations;
    reprojection_px : per point the (k,) reprojection errors at ``xyz``.
    """

    names: list[str]
    xyz: np.ndarray
    n_observations: np.ndarray
    usable: np.ndarray
    image_ids: list[np.ndarray] = field(default_factory=list)
    observations_px: list[np.ndarray] = field(default_factory=list)
    reprojection_px: list[np.ndarray] = field(default_factory=list)


def _image_index(rec: pycolmap.Reconstruction) -> dict[str, int]:
    """Image name (and base name, where unique) -> registered image id."""
    by_name: dict[str, int] = {}
    base: dict[str, list[int]] = {}
    for image_id in rec.reg_image_ids():
        name = rec.images[image_id].name
        by_name[name] = image_id
        base.setdefault(name.rsplit("/", 1)[-1], []).append(image_id)
    for b, ids in base.items():
        if len(ids) == 1:
            by_name.setdefault(b, ids[0])
    return by_name


def _rays(rec, ids, xy) -> tuple[np.ndarray, np.ndarray]:
    """(k, 3) camera centres and unit world ray directions."""
    C, D = [], []
    for image_id, p in zip(ids, xy, strict=True):
        image = rec.images[image_id]
        pose = image.cam_from_world()
        R = pose.rotation.matrix()
        d = np.r_[image.camera.cam_from_img(p[None])[0], 1.0] @ R
        C.append(-R.T @ pose.translation)
        D.append(d / np.linalg.norm(d))
    return np.array(C), np.array(D)


def _reproject(rec, ids, X) -> tuple[np.ndarray, np.ndarray]:
    """(k, 2) projections of X and (k,) depths."""
    uv, depth = [], []
    for image_id in ids:
        image = rec.images[image_id]
        Xc = image.cam_from_world() * X
        depth.append(Xc[2])
        uv.append(image.camera.img_from_cam(Xc[None])[0] if Xc[2] > 0 else [np.nan] * 2)
    return np.array(uv, float), np.array(depth)


def _refine(rec, ids, xy, X, iterations: int = 10) -> np.ndarray:
    """Gauss-Newton on the reprojection error, numeric Jacobian (3 columns)."""
    for _ in range(iterations):
        r0 = (_reproject(rec, ids, X)[0] - xy).ravel()
        if not np.all(np.isfinite(r0)):
            return X
        scale = max(1e-4 * np.linalg.norm(X - _rays(rec, ids, xy)[0].mean(0)), 1e-6)
        J = np.empty((len(r0), 3))
        for a in range(3):
            e = np.zeros(3)
            e[a] = scale
            J[:, a] = ((_reproject(rec, ids, X + e)[0] - xy).ravel() - r0) / scale
        step = np.linalg.lstsq(J, -r0, rcond=None)[0]
        X = X + step
        if np.linalg.norm(step) < 1e-9 * max(np.linalg.norm(X), 1.0):
            break
    return X


def triangulate_control_points(
    reconstruction: pycolmap.Reconstruction,
    points: ControlPoints,
    min_observations: int = 2,
) -> ControlTriangulation:
    """Triangulate each control point from its observations in registered images.

    Observations naming images that are not registered in the model are
    skipped with one warning per image, as OpenSfM does.
    """
    index = _image_index(reconstruction)
    unknown: set[str] = set()
    n = len(points)
    out = ControlTriangulation(
        names=points.names(),
        xyz=np.full((n, 3), np.nan),
        n_observations=np.zeros(n, int),
        usable=np.zeros(n, bool),
    )
    for k, point in enumerate(points.points):
        ids, xy = [], []
        for ob in point.observations:
            image_id = index.get(ob.image_name)
            if image_id is None:
                unknown.add(ob.image_name)
                continue
            ids.append(image_id)
            xy.append(ob.xy)
        ids_a, xy_a = np.array(ids, int), np.array(xy, float).reshape(-1, 2)
        out.image_ids.append(ids_a)
        out.observations_px.append(xy_a)
        out.n_observations[k] = len(ids)
        out.reprojection_px.append(np.full(len(ids), np.nan))
        if len(ids) < max(min_observations, 2):
            continue
        C, D = _rays(reconstruction, ids_a, xy_a)
        P = np.eye(3)[None] - D[:, :, None] * D[:, None, :]
        X = np.linalg.solve(P.sum(0), np.einsum("kij,kj->i", P, C))
        cosines = D @ D.T
        angle = np.degrees(np.arccos(np.clip(cosines.min(), -1.0, 1.0)))
        if angle < MIN_TRIANGULATION_ANGLE_DEG:
            continue
        X = _refine(reconstruction, ids_a, xy_a, X)
        uv, depth = _reproject(reconstruction, ids_a, X)
        if np.any(depth <= 0):
            continue
        out.xyz[k] = X
        out.usable[k] = True
        out.reprojection_px[k] = np.linalg.norm(uv - xy_a, axis=1)
    for name in sorted(unknown):
        logger.warning(
            "%s: image %s is not registered in the model; its control point "
            "observations are skipped",
            points.source.name if points.source else "control points",
            name,
        )
    return out


def require_usable(
    tri: ControlTriangulation, minimum: int, source, what: str = "control points"
) -> None:
    """InputError unless at least ``minimum`` points are usable."""
    if int(tri.usable.sum()) < minimum:
        raise InputError(
            source,
            f"{int(tri.usable.sum())} usable {what} (observed in >= 2 registered "
            f"images and triangulable) of {len(tri.names)}; at least {minimum} needed",
        )
