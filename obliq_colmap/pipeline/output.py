"""The run's output: the result block (:func:`result_block`), the
constrained points with tracks (:func:`constrained_points`), the JSON report
(:func:`run_report`) and its closing table (:func:`summary_table`), all
written atomically by :func:`write_run`.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from obliq_colmap import __version__
from obliq_colmap.adjustment import (
    Stage3,
    TiePointOptions,
    heights_on_vertical,
    tie_points,
)
from obliq_colmap.bundle import BundleProblem, BundleResult
from obliq_colmap.bundle.facade_lines import rotate
from obliq_colmap.cadastre import visible_corners
from obliq_colmap.colmap_io import Block, Georef, ImageRecord, Point3D, write_result
from obliq_colmap.errors import InputError
from obliq_colmap.geometry import Camera, lines_through, point_line_distance
from obliq_colmap.images import read_image
from obliq_colmap.report import uncertainty_report
from obliq_colmap.state import BlockState, ImageOutcome, Inputs, json_float

__all__ = [
    "REPORT_FILE",
    "RunResult",
    "color_points",
    "constrained_points",
    "result_block",
    "run_report",
    "summary_table",
    "bundle_tie_records",
    "tie_point_records",
    "write_run",
]

REPORT_FILE = "report.json"


@dataclass
class RunResult:
    """Everything :func:`run_register` produced (before writing)."""

    block: Block  # registered images only, local frame of ``georef``
    georef: Georef
    points3D: list[Point3D]
    outcomes: dict[int, ImageOutcome]
    report: dict[str, Any]
    bundle: BundleResult | None = None
    #: Per image id, the lens stage 2 started from after the per-image
    #: stages (the head's median lens once the head pass ran, None: the
    #: priors'), from which the block stage places the images it lacks: with
    #: ``outcomes``, what the block stage starts from.
    starts: dict[int, Camera | None] = field(default_factory=dict)


def result_block(inputs: Inputs, state: BlockState) -> Block:
    """The registered images with their poses and intrinsics.

    After the bundle the images of one head share its camera (as in the
    priors); a per-image result gives every image its own camera (id = the
    image id), since stage 2 refines the focal length per image.
    """
    images, cameras = {}, {}
    for i, pose in state.poses.items():
        prior = inputs.priors.images[i]
        # in the result's camera model (--camera_model), as after the bundle
        cam = state.cameras[i].with_model(inputs.cameras[prior.camera_id].model)
        cid = prior.camera_id if state.shared else i
        cameras[cid] = Camera(cam.model, cam.width, cam.height, cam.params, cid)
        images[i] = ImageRecord(i, prior.name, cid, pose)
    return Block(dict(sorted(cameras.items())), images)


def _observations(
    block: Block, image_id: int, X: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Where points (N, 3) project in an image: (kept (K,) indices, (K, 2) px),
    only those in front of the camera and inside the image."""
    im = block.images[image_id]
    cam = block.cameras[im.camera_id]
    Xc = im.cam_from_world.transform(X)
    with np.errstate(divide="ignore", invalid="ignore"):
        px = cam.img_from_cam(Xc)
    inside = (
        (Xc[:, 2] > 0)
        & np.all(np.isfinite(px), axis=1)
        & (px[:, 0] >= 0)
        & (px[:, 1] >= 0)
        & (px[:, 0] <= cam.width)
        & (px[:, 1] <= cam.height)
    )
    keep = np.flatnonzero(inside)
    return keep, px[keep]


def _measured(
    inputs: Inputs, outcome: ImageOutcome, corners: np.ndarray, px: np.ndarray
) -> np.ndarray:
    """(K, 2) observations of ``corners`` (K,): where stage 2 matched a corner
    to a vertical segment, its projection ``px`` moved across onto that
    segment's line in the raw image, so that the observation is measured
    (its reprojection error is the line residual) and not the projection
    itself; the other corners (visible, not matched) keep their projection.
    The segments are in the priors' undistorted pixels; distorting them
    with the priors' camera gives raw pixels, which no camera change moves."""
    reg = outcome.registration
    if reg is None or not len(reg.inlier_pairs):
        return px
    where = {int(c): k for k, c in enumerate(reg.inlier_pairs[:, 0])}
    rows = np.array([where.get(int(c), -1) for c in corners])
    has = rows >= 0
    if not has.any():
        return px
    camera = inputs.priors.cameras[inputs.priors.images[outcome.image_id].camera_id]
    ends = camera.distort_pixels(reg.inlier_segments_px[rows[has]].reshape(-1, 2))
    ends = ends.reshape(-1, 2, 2)
    out = px.copy()
    out[has] = _onto_lines(px[has], ends)
    return out


def _onto_lines(px: np.ndarray, ends: np.ndarray) -> np.ndarray:
    """(K, 2) points ``px`` moved across onto the lines through the segments
    ``ends`` (K, 2, 2), along each line's normal."""
    lines = lines_through(ends[:, 0], ends[:, 1])
    return px - point_line_distance(px, lines)[:, None] * lines[:, :2]


def _facade_observations(
    block: Block, stage3: Stage3, F: np.ndarray
) -> list[list[tuple[int, np.ndarray]]]:
    """Per facade track point ``F`` (J, 3): its observations, (image id, raw
    px) in every image of the track that the output keeps, each where the
    bundle measured it: the point's projection moved across onto the line of
    that image's segment (its reprojection error is then the line residual).
    Only the observations the last solve kept (not its outliers); where an
    image holds two of one track, the one nearest the projection."""
    t = stage3.tracks
    kept = stage3.kept_observations
    use = np.zeros(t.num_observations, bool)
    use[np.arange(t.num_observations) if kept is None else kept] = True
    fobs: list[list[tuple[int, np.ndarray]]] = [[] for _ in range(len(F))]
    for k, i in enumerate(stage3.ids):
        if i not in block.images:  # left out after the bundle
            continue
        sel = np.flatnonzero((t.image == k) & use)
        keep, px = _observations(block, i, F[t.track[sel]])
        sel = sel[keep]
        on = _onto_lines(px, stage3.ends_raw[sel])
        # nearest first, then the first of each track
        order = np.argsort(np.linalg.norm(on - px, axis=1), kind="stable")
        _, first = np.unique(t.track[sel][order], return_index=True)
        for h in order[first]:
            fobs[t.track[sel[h]]].append((i, on[h]))
    return fobs


def _segment_bottoms(
    inputs: Inputs, block: Block, outcome: ImageOutcome
) -> tuple[np.ndarray, np.ndarray]:
    """Where the vertical segments stage 2 matched in one image end at the
    bottom, as heights on their corners' verticals through the image's FINAL
    pose and camera (``block``): (K,) corners, (K,) heights (NaN where the
    ray misses). The segments are in the priors' undistorted pixels (see
    :func:`_measured`); their raw pixels do not move with the bundle."""
    reg = outcome.registration
    if reg is None or not len(reg.inlier_pairs):
        return np.zeros(0, int), np.zeros(0)
    prior = inputs.priors.cameras[inputs.priors.images[outcome.image_id].camera_id]
    ends = prior.distort_pixels(reg.inlier_segments_px.reshape(-1, 2))
    ends = ends.reshape(-1, 2, 2)
    im = block.images[outcome.image_id]
    corners = reg.inlier_pairs[:, 0].astype(int)
    xy = inputs.cadastre.corner_xy[corners]
    cam = block.cameras[im.camera_id]
    h = np.column_stack(
        [heights_on_vertical(cam, im.cam_from_world, xy, ends[:, k]) for k in (0, 1)]
    )
    # the lower end is the bottom (the end nearer the nadir)
    with np.errstate(invalid="ignore"):
        return corners, np.min(h, axis=1)


def _rebased_planes(
    inputs: Inputs,
    block: Block,
    state: BlockState,
    outcomes: dict[int, ImageOutcome],
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The images' ground planes in the written block's datum, and the
    ground the matched segments' bottoms measure at the final poses.

    Stage 2 fitted each image's plane to its matched segments' bottoms at
    ITS pose; the datum correction shifts the plane before the bundle, but
    the bundle then moves each camera by metres along its view (focal and
    height trade) and the planes stay. Each plane is rebased here by the
    median of (bottom - plane) over its matched corners (the median offset
    of the others where it has none). Measured on ``houses-102`` (focal 8 %
    off in the priors): the planes sat off the true ground by per-image
    offsets of -13 to +57 m (MAD 4.3 m over the matched views), the bottoms
    at the final poses by 0.0 m (MAD 0.36 m).

    Returns
    -------
    planes : (I, 3) rebased ``z = a x + b y + c``, images in
        ``sorted(block.images)`` order.
    corners, heights : (K,) every matched (corner, image) pair's corner and
        bottom height (:func:`_segment_bottoms`).
    """
    xy = inputs.cadastre.corner_xy
    ids = sorted(block.images)
    planes = np.array([state.planes[i] for i in ids], float).reshape(-1, 3)
    obs_c, obs_h, offset = [], [], np.full(len(ids), np.nan)
    for k, i in enumerate(ids):
        c, h = _segment_bottoms(inputs, block, outcomes[i])
        ok = np.isfinite(h)
        c, h = c[ok], h[ok]
        if len(c):
            offset[k] = np.median(h - (xy[c] @ planes[k, :2] + planes[k, 2]))
        obs_c.append(c)
        obs_h.append(h)
    has = np.isfinite(offset)
    offset[~has] = np.median(offset[has]) if has.any() else 0.0
    planes[:, 2] += offset
    c = np.concatenate(obs_c) if obs_c else np.zeros(0, int)
    h = np.concatenate(obs_h) if obs_h else np.zeros(0)
    return planes, c, h


def _local_planes(
    xy: np.ndarray, xy_meas: np.ndarray, z_meas: np.ndarray, k: int = 16
) -> np.ndarray:
    """(Q,) heights at xy (Q, 2) of the plane through the ``k`` nearest
    measured points (xy_meas (M, 2), z_meas (M,), M >= 3), least squares
    with one round that drops residuals beyond 3 times their median."""
    k = min(k, len(z_meas))
    _, nn = cKDTree(xy_meas).query(xy, k)
    nn = nn.reshape(len(xy), k)
    d = xy_meas[nn] - xy[:, None, :]  # (Q, k, 2), the query at the origin
    A = np.concatenate([d, np.ones(d.shape[:2] + (1,))], axis=2)  # (Q, k, 3)
    z = z_meas[nn]
    w = np.ones(z.shape)
    # a small ridge on the slopes (m^2) for corners along one straight street
    ridge = np.diag([1.0, 1.0, 0.0])
    for _ in range(2):
        N = np.einsum("qk,qki,qkj->qij", w, A, A) + ridge
        coef = np.linalg.solve(N, np.einsum("qk,qki,qk->qi", w, A, z)[..., None])
        r = np.abs(z - np.einsum("qki,qi->qk", A, coef[..., 0]))
        w = (r <= 3.0 * np.median(r, axis=1, keepdims=True) + 1e-9).astype(float)
    return coef[:, 2, 0]


def _corner_ground(
    xy: np.ndarray,
    planes: np.ndarray,
    corners: np.ndarray,
    heights: np.ndarray,
    seen: np.ndarray,
) -> np.ndarray:
    """(C,) ground height of every map corner (xy: (C, 2)).

    A corner with bottoms (``corners``, ``heights``: (K,), from
    :func:`_rebased_planes`): their median. Any other: the plane through
    the nearest 16 measured corners (:func:`_local_planes`); with fewer
    than 3 measured corners, the mean of the rebased ``planes`` (I, 3) of
    the images that see it (``seen``: (C, I) bool), else of all images.
    On ``houses-102`` (3 deg slope) the unmeasured corners came 1.33 m
    (median |error|) off the true ground from the images' planes (a plane
    per image is a fit over its whole view, ridge-damped in slope), 0.26 m
    from the local planes.
    """
    h = xy @ planes[:, :2].T + planes[:, 2]  # (C, I)
    w = seen.astype(float)
    w[w.sum(axis=1) == 0] = 1.0
    ground = (h * w).sum(axis=1) / w.sum(axis=1)
    if len(corners) == 0:
        return ground
    # per corner the median of its bottoms: sort, split
    order = np.lexsort((heights, corners))
    c, z = corners[order], heights[order]
    uc, start, n = np.unique(c, return_index=True, return_counts=True)
    zc = 0.5 * (z[start + (n - 1) // 2] + z[start + n // 2])
    rest = np.setdiff1d(np.arange(len(xy)), uc)
    if len(uc) >= 3 and len(rest):
        ground[rest] = _local_planes(xy[rest], xy[uc], zc)
    ground[uc] = zc
    return ground


def constrained_points(
    inputs: Inputs,
    block: Block,
    state: BlockState,
    outcomes: dict[int, ImageOutcome],
    bundle: BundleResult | None = None,
    stage3: Stage3 | None = None,
) -> list[Point3D]:
    """The constrained points with tracks, for COLMAP's dense stages.

    * Map corners at their ground heights (:func:`_corner_ground`, in the
      block's final datum), observed where they project in
      every image in which the corner is potentially visible
      (:func:`cadastre.visible_corners`: inside the image, an adjacent wall
      facing the camera). Occlusion by other buildings is not tested.
    * After the bundle, every facade track's point ``x_j + h_j z`` (with the
      facade lines, the line's point nearest the anchor ``x_j``), observed
      on its segment's line in the images of the track
      (:func:`_facade_observations`).

    Points seen in fewer than two images are dropped (COLMAP's dense stages
    need shared points).
    """
    cad = inputs.cadastre
    ids = sorted(block.images)
    if not ids:
        return []
    planes, bottom_c, bottom_h = _rebased_planes(inputs, block, state, outcomes)
    visible = []
    for k, i in enumerate(ids):
        im = block.images[i]
        p = planes[k]
        visible.append(
            visible_corners(
                cad,
                block.cameras[im.camera_id],
                im.cam_from_world,
                lambda xy, p=p: xy @ p[:2] + p[2],
                (0.0, 0.5),
            )
        )
    seen = np.zeros((cad.num_corners, len(ids)), bool)
    for k, vis in enumerate(visible):
        seen[vis, k] = True
    ground = _corner_ground(cad.corner_xy, planes, bottom_c, bottom_h, seen)
    X = np.column_stack([cad.corner_xy, ground])
    obs: list[list[tuple[int, np.ndarray]]] = [[] for _ in range(len(X))]
    for i, vis in zip(ids, visible, strict=True):
        keep, px = _observations(block, i, X[vis])
        px = _measured(inputs, outcomes[i], vis[keep], px)
        for c, p in zip(vis[keep], px, strict=True):
            obs[c].append((i, p))
    points = _one_point_per_place(X, obs, cad.corner_xy)
    if bundle is not None and stage3 is not None:
        t = stage3.tracks
        xy = t.anchor_xy
        if len(bundle.facade_offsets):  # the facade lines' solved offsets
            normal = rotate(inputs.cadastre.edge_normal[t.edge], bundle.facade_angles)
            xy = xy + bundle.facade_offsets[:, None] * normal
        F = np.column_stack([xy, bundle.facade_heights])
        fobs = _facade_observations(block, stage3, F)
        points += [Point3D(F[j], o) for j, o in enumerate(fobs) if len(o) >= 2]
    return points


def color_points(image_path, block: Block, points: list[Point3D]) -> None:
    """Give each point (in place) the median RGB colour of the pixels at its
    observations; one image in memory at a time."""
    per_image: dict[int, list[tuple[int, np.ndarray]]] = {}
    for k, p in enumerate(points):
        for i, xy in p.observations:
            per_image.setdefault(i, []).append((k, xy))
    samples: list[list[np.ndarray]] = [[] for _ in points]
    for i, obs in per_image.items():
        image, _ = read_image(image_path / block.images[i].name, color=True)
        if image is None:
            continue
        H, W = image.shape[:2]
        xy = np.array([o[1] for o in obs])
        # COLMAP pixel (x, y) covers [x - 0.5, x + 0.5): the pixel is floor(x)
        col = np.clip(np.floor(xy[:, 0]).astype(int), 0, W - 1)
        row = np.clip(np.floor(xy[:, 1]).astype(int), 0, H - 1)
        rgb = image[row, col, ::-1]
        for (k, _), c in zip(obs, rgb, strict=True):
            samples[k].append(c)
    for p, s in zip(points, samples, strict=True):
        if s:
            p.color = np.median(np.array(s), axis=0).astype(np.uint8)


#: Map corners closer than this (m) are one physical corner: a vertex shared
#: by two footprints (a party wall's end), digitised once per footprint.
SAME_CORNER_M = 0.05


def _one_point_per_place(
    X: np.ndarray, obs: list[list[tuple[int, np.ndarray]]], corner_xy: np.ndarray
) -> list[Point3D]:
    """One point per physical corner: corners (C,) within ``SAME_CORNER_M``
    of each other merged (mean position, one observation per image), kept
    where seen in at least two images. X (C, 3); corner_xy (C, 2)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components
    from scipy.spatial import cKDTree

    pairs = cKDTree(corner_xy).query_pairs(SAME_CORNER_M, output_type="ndarray")
    C = len(corner_xy)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), (C, C))
    _, label = connected_components(graph, directed=False)
    points = []
    for members in np.split(
        np.argsort(label, kind="stable"), np.cumsum(np.bincount(label))[:-1]
    ):
        seen: dict[int, np.ndarray] = {}
        for c in members:
            for i, p in obs[c]:
                seen.setdefault(i, p)
        if len(seen) >= 2:
            points.append(Point3D(X[members].mean(axis=0), list(seen.items())))
    return points


def bundle_tie_records(
    problem: BundleProblem, result: BundleResult, image_ids: set[int]
) -> list[Point3D]:
    """The tie points the bundle solved, with their observations (those its
    outlier rounds kept) in the images written (``image_ids``), seen at
    least twice, in the block's frame."""
    ids = np.asarray(problem.image_ids)[problem.tie_image]
    keep = np.isin(ids, list(image_ids))
    point, ids, xy = problem.tie_point[keep], ids[keep], problem.tie_xy[keep]
    order = np.argsort(point, kind="stable")
    point, ids, xy = point[order], ids[order], xy[order]
    starts = np.searchsorted(point, np.arange(len(result.tie_xyz) + 1))
    return [
        Point3D(
            result.tie_xyz[t].copy(),
            [(int(ids[k]), xy[k]) for k in range(starts[t], starts[t + 1])],
        )
        for t in range(len(result.tie_xyz))
        if starts[t + 1] - starts[t] >= 2
    ]


def tie_point_records(
    inputs: Inputs, block: Block, ground_z: float, options: TiePointOptions
) -> list[Point3D]:
    """SIFT tie points of the registered block (:func:`adjustment.tie_points`)
    with their tracks at the measured pixels, in the block's frame."""
    ids = sorted(block.images)
    gray = [read_image(inputs.image_path / block.images[i].name)[0] for i in ids]
    cams = [block.cameras[block.images[i].camera_id].to_pycolmap() for i in ids]
    poses = [block.images[i].cam_from_world.to_rigid3d() for i in ids]
    ties = tie_points(gray, cams, poses, ground_z, options)
    order = np.argsort(ties.obs_point, kind="stable")
    starts = np.searchsorted(ties.obs_point[order], np.arange(len(ties.xyz) + 1))
    image_ids = np.asarray(ids)[ties.obs_image[order]]
    xy = ties.obs_xy[order]
    return [
        Point3D(
            ties.xyz[t],
            [(int(image_ids[k]), xy[k]) for k in range(starts[t], starts[t + 1])],
        )
        for t in range(len(ties.xyz))
    ]


def run_report(
    inputs: Inputs,
    outcomes: list[ImageOutcome],
    rescued: list[str],
    bundle: BundleResult | None,
    georef: Georef,
    timings: dict[str, float],
) -> dict[str, Any]:
    """The JSON run report: per image, per stage, the bundle's summary and
    the cameras' uncertainty (:func:`obliq_colmap.report.uncertainty_report`)."""
    images = {}
    for o in outcomes:
        r = o.registration
        images[o.name] = {
            "image_id": o.image_id,
            "status": o.status,
            "message": o.message,
            "vp_status": o.vp_status,
            "vertical_source": r.vertical_source if r is not None else None,
            "num_segments": int(len(o.segments)),
            "num_candidates": r.num_candidates if r is not None else 0,
            "num_inlier_corners": r.num_inliers if r is not None else 0,
            "chance_inlier_corners": r.chance_inliers if r is not None else -1,
            "inlier_ratio": r.inlier_ratio if r is not None else 0.0,
            "ransac_trials": r.num_trials if r is not None else 0,
            "residual_rms_px": json_float(r.residual_rms_px) if r is not None else None,
            "ground_height_m": json_float(r.ground_height) if r is not None else None,
            "rescued": o.rescued,
            "reregistered": o.reregistered,
            "time_s": {k: round(v, 4) for k, v in o.time_s.items()},
        }
    report: dict[str, Any] = {
        "software": f"obliq-colmap {__version__}",
        "image_path": str(inputs.image_path),
        "cadastre_path": str(inputs.cadastre_path),
        "georef": georef.to_json(),
        "num_images": len(outcomes),
        "num_registered": sum(o.registered for o in outcomes),
        "left_out": {o.name: o.message for o in outcomes if not o.registered},
        "rescued": rescued,
        "time_s": {k: round(v, 3) for k, v in timings.items()},
        "images": images,
    }
    if bundle is not None:
        s = bundle.summary
        report["bundle"] = {
            "brief": s.brief(),
            "num_vertical": s.num_vertical,
            "num_horizontal": s.num_horizontal,
            "num_heights": s.num_heights,
            "rmse_vertical_px": [s.initial_rmse_vertical_px, s.final_rmse_vertical_px],
            "rmse_horizontal_px": [
                json_float(s.initial_rmse_horizontal_px),
                json_float(s.final_rmse_horizontal_px),
            ],
            "iterations": s.num_iterations,
            "termination": s.termination,
            "components": [list(c) for c in s.components],
            # A-posteriori variance of unit weight (residuals weighted by
            # their kind's sigma): ~1 where the sigmas fit the residuals.
            "variance_factor": json_float(bundle.variance_factor),
            # Per observation group: its own factor and redundancy (the
            # precision's covariance is their sandwich).
            "variance_components": {
                k: [json_float(v), json_float(r)]
                for k, (v, r) in bundle.variance_components.items()
            },
            # With --bundle_position_sigma: how far the priors' centres sit
            # off the map horizontally (priors minus solved, m).
            "prior_offset_m": (
                None
                if bundle.prior_offset_m is None
                else [round(float(v), 4) for v in bundle.prior_offset_m]
            ),
        }
        names = {o.image_id: o.name for o in outcomes if o.registered}
        report["uncertainty"] = uncertainty_report(bundle, names)
    return report


def summary_table(report: dict[str, Any]) -> str:
    """The closing table of a run, one line per image."""
    facades = report.get("facades", {}).get("images", {})
    head = (
        "image",
        "vp",
        "segments",
        "corners",
        "rms px",
        "facade obs",
        "bundle v/h",
        "sd px",
    )
    rows = [(*head, "status")]
    for name, r in report["images"].items():
        rms = r["residual_rms_px"]
        status = r["status"] + (" (rescued)" if r["rescued"] else "")
        status += " (against the block)" if r.get("reregistered") else ""
        if r["message"]:
            status += f": {r['message']}"
        f = facades.get(name, {})
        brms = [x for x in f.get("bundle_rms_px", []) if x is not None]
        sd = f.get("bundle_precision_px")
        rows.append(
            (
                name,
                r["vp_status"] or "-",
                str(r["num_segments"]),
                str(r["num_inlier_corners"]),
                f"{rms:.2f}" if rms is not None else "-",
                str(f["observations"]) if f else "-",
                "/".join(f"{x:.2f}" for x in brms) if len(brms) == 2 else "-",
                f"{sd:.2f}" if sd is not None else "-",
                status,
            )
        )
    n = len(head)
    widths = [max(len(row[k]) for row in rows) for k in range(n)]
    lines = [
        "  ".join(c.ljust(w) for c, w in zip(row[:n], widths, strict=True))
        + "  "
        + row[n]
        for row in rows
    ]
    lines.append(
        f"registered {report['num_registered']}/{report['num_images']} images"
        f" in {report['time_s'].get('total', math.nan):.1f} s"
    )
    return "\n".join(lines)


def write_run(output_path: str | Path, run: RunResult) -> Path:
    """Write the model, georef.json and report.json atomically.

    Raises
    ------
    InputError
        The output folder exists and is not empty, or no image was registered.
    """
    if not run.block.images:
        raise InputError(output_path, "no image could be registered; nothing written")
    text = json.dumps(run.report, indent=2, default=_json_default) + "\n"
    return write_result(
        output_path, run.block, run.georef, run.points3D, {REPORT_FILE: text}
    )


def _json_default(x):
    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, Path):
        return str(x)
    raise TypeError(f"not JSON serialisable: {type(x)}")
