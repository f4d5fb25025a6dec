"""The constraints of a registration read back from its model.

``register`` writes two kinds of constrained point into points3D (see
:func:`obliq_colmap.pipeline.output.constrained_points`): the map corners at
their recovered ground heights, and one point ``x_j + h_j z`` per facade
track, ``x_j`` on a map edge. Which point is which is recovered here from the
map: a point on a map corner (within ``corner_tol_m``) is a ground corner,
a point on a map edge otherwise is a facade track of every footprint whose
boundary passes there (party walls belong to two buildings).
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap
import shapely
from scipy.spatial import cKDTree

from obliq_colmap.cadastre import Cadastre, load_cadastre
from obliq_colmap.colmap_io import Georef, read_georef
from obliq_colmap.errors import InputError

__all__ = ["ModelConstraints", "load_constraints", "split_points"]

logger = logging.getLogger(__name__)


@dataclass
class ModelConstraints:
    """A registration's constraints on the map, LOCAL frame of ``georef``.

    Attributes
    ----------
    georef : the model's georeference (world_abs = local + origin).
    cadastre : the map in the same local frame.
    corner_index : (G,) int, cadastre corner of each ground point.
    ground_xyz : (G, 3) ground corners (x, y, recovered ground height).
    facade_xyz : (F, 3) facade track points (x_j, y_j, h_j).
    facade_building : (P, 2) int pairs (facade point, cadastre building).
    facade_edge : (P,) int, the map edge (wall) of each pair.
    other_xyz : (T, 3) the other points (the bundle's tie points).
    other_error : (T,) their reprojection errors (px).
    other_m_per_px : (T,) metres per pixel at each of them (depth in its
        first observation's image over that camera's focal length).
    facade_top_m : how far above the ground ``register`` looked for facade
        edges (its ``report.json``), None where the model does not say.
    """

    georef: Georef
    cadastre: Cadastre
    corner_index: np.ndarray
    ground_xyz: np.ndarray
    facade_xyz: np.ndarray
    facade_building: np.ndarray
    facade_edge: np.ndarray
    other_xyz: np.ndarray
    other_error: np.ndarray
    other_m_per_px: np.ndarray
    facade_top_m: float | None = None


def read_points(model_path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """points3D of a COLMAP model (binary or text), model frame: xyz (N, 3),
    reprojection error (N,) px, and metres per pixel at each point (N,):
    its depth in its first observation's image over that camera's mean
    focal length."""
    try:
        rec = pycolmap.Reconstruction(str(model_path))
    except Exception as exc:  # pycolmap raises plain RuntimeError / ValueError
        raise InputError(model_path, f"not a readable COLMAP model: {exc}") from None
    pts = list(rec.points3D.values())
    xyz = np.asarray([p.xyz for p in pts], float).reshape(-1, 3)
    err = np.asarray([p.error for p in pts], float)
    if not pts:
        return xyz, err, np.zeros(0)
    first = np.asarray([p.track.elements[0].image_id for p in pts], int)
    ids = np.asarray(sorted(rec.images), int)
    R = np.stack([rec.images[i].cam_from_world().rotation.matrix() for i in ids])
    t = np.stack([rec.images[i].cam_from_world().translation for i in ids])
    f = np.asarray(
        [rec.cameras[rec.images[i].camera_id].mean_focal_length() for i in ids]
    )
    k = np.searchsorted(ids, first)
    depth = np.einsum("nj,nj->n", R[k, 2], xyz) + t[k, 2]
    return xyz, err, depth / f[k]


def split_points(
    cadastre: Cadastre,
    xyz: np.ndarray,
    corner_tol_m: float = 1e-3,
    edge_tol_m: float = 0.02,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tell ground corners from facade points.

    Parameters
    ----------
    xyz : (N, 3) constrained points, local frame.

    Returns
    -------
    corner_index : (N,) int, the cadastre corner a point sits on, -1 if none.
    pairs : (P, 3) int, (point, building, edge) for points on a building's
        outline (on map edge ``edge``) that are not corners; one row per
        point and building.
    on_edge : (N,) bool.
    """
    tree = cKDTree(cadastre.corner_xy)
    d, k = tree.query(xyz[:, :2])
    corner_index = np.where(d <= corner_tol_m, k, -1)
    rest = np.flatnonzero(corner_index < 0)
    strtree = shapely.STRtree(shapely.linestrings(cadastre.edge_xy))
    pt, e = strtree.query(
        shapely.points(xyz[rest, :2]), predicate="dwithin", distance=edge_tol_m
    )
    pairs = np.column_stack([rest[pt], cadastre.edge_building[e], e]).astype(int)
    pairs = pairs.reshape(-1, 3)
    # a point near a corner touches both of its edges: one row per building
    _, first = np.unique(pairs[:, :2], axis=0, return_index=True)
    pairs = pairs[np.sort(first)]
    on_edge = np.zeros(len(xyz), bool)
    on_edge[pairs[:, 0]] = True
    return corner_index, pairs, on_edge


def load_constraints(
    input_path: str | Path, cadastre_path: str | Path
) -> ModelConstraints:
    """Read OUT_MODEL (points3D, georef.json) and the map it was registered to.

    Raises
    ------
    InputError
        No model or no georef.json in ``input_path``; no constrained point on
        the map (another map than the registration's?).
    """
    input_path = Path(input_path)
    if not (input_path / "georef.json").is_file():
        raise InputError(input_path, "no georef.json: not an obliq-colmap result model")
    georef = read_georef(input_path)
    cadastre = load_cadastre(cadastre_path, origin=georef.origin)
    xyz, err, m_per_px = read_points(input_path)
    corner_index, pairs, on_edge = split_points(cadastre, xyz)
    is_corner = corner_index >= 0
    if not is_corner.any() and not on_edge.any():
        raise InputError(
            cadastre_path,
            f"none of the model's {len(xyz)} points lies on this map's footprints; "
            "give the map the model was registered to",
        )
    facade_ids = np.flatnonzero(on_edge)
    remap = np.full(len(xyz), -1)
    remap[facade_ids] = np.arange(len(facade_ids))
    logger.info(
        "%d ground corners, %d facade points, %d others ignored",
        is_corner.sum(),
        len(facade_ids),
        len(xyz) - is_corner.sum() - len(facade_ids),
    )
    return ModelConstraints(
        georef=georef,
        cadastre=cadastre,
        corner_index=corner_index[is_corner],
        ground_xyz=xyz[is_corner],
        facade_xyz=xyz[facade_ids],
        facade_building=np.column_stack([remap[pairs[:, 0]], pairs[:, 1]]),
        facade_edge=pairs[:, 2],
        other_xyz=xyz[~is_corner & ~on_edge],
        other_error=err[~is_corner & ~on_edge],
        other_m_per_px=m_per_px[~is_corner & ~on_edge],
        facade_top_m=_facade_top(input_path),
    )


def _facade_top(input_path: Path) -> float | None:
    """The top of ``register``'s facade search (m above the ground) from
    the model's ``report.json``; None where it is absent or does not say."""
    try:
        report = json.loads((input_path / "report.json").read_text())
        return float(report["options"]["facade_height_range_m"][1])
    except (OSError, ValueError, KeyError, TypeError, IndexError):
        return None
