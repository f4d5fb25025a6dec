"""The evaluation of a block, pure and without files: :func:`evaluate_block`
(match by name, the vertical offset, rotation and centre errors, corner
deviations, statuses and the summary)."""

from __future__ import annotations

import logging
import math

import numpy as np

from obliq_colmap.colmap_io import Block
from obliq_colmap.evaluate.measure import (
    corner_deviations_px,
    mean_deviation_by_offset,
    scene_height_offset,
    search_block_offset,
)
from obliq_colmap.evaluate.results import (
    STATUS_BEHIND,
    STATUS_FAILED,
    STATUS_MISSING,
    STATUS_NO_CORNERS,
    STATUS_REGISTERED,
    EvaluateOptions,
    Evaluation,
    EvaluationSummary,
    ImageEvaluation,
    offset_label,
)
from obliq_colmap.geometry import rotation_angle_deg

logger = logging.getLogger(__name__)


def _image_offset(
    est: Block,
    gt: Block,
    est_id: int,
    gt_id: int,
    corners: np.ndarray,
    kind: str,
) -> float:
    """One image's own vertical offset (m, ``EvaluateOptions.vertical_offset``)
    in a common frame; its centre-height difference where the corners give
    none."""
    e, g = est.images[est_id], gt.images[gt_id]
    dz = e.cam_from_world.center[2] - g.cam_from_world.center[2]
    if kind == "cameras" or len(corners) == 0:
        return float(dz)
    d = scene_height_offset(
        est.cameras[e.camera_id],
        e.cam_from_world,
        gt.cameras[g.camera_id],
        g.cam_from_world,
        corners,
        dz,
    )
    return d if math.isfinite(d) else float(dz)


def _searched_offset(
    est: Block,
    gt: Block,
    est_by_name: dict,
    gt_by_name: dict,
    corners: np.ndarray,
    visible_idx: dict[str, np.ndarray],
    camera_offset: float,
    options: EvaluateOptions,
) -> float:
    """``vertical_offset="search"``: :func:`search_block_offset` over the
    images with visible corners, in the common frame of ``est`` and ``gt``."""
    profiles, missing = [], 0
    for name in sorted(gt_by_name):
        idx = visible_idx.get(name, np.zeros(0, int))
        if idx.size == 0:
            continue  # not measurable, not in the median
        if name not in est_by_name:
            missing += 1
            continue
        e = est.images[est_by_name[name].image_id]
        g = gt.images[gt_by_name[name].image_id]
        profiles.append(
            mean_deviation_by_offset(
                est.cameras[e.camera_id],
                e.cam_from_world,
                gt.cameras[g.camera_id],
                g.cam_from_world,
                corners[idx],
                options.across_vertical,
            )
        )
    if not profiles:
        return camera_offset
    offset, _ = search_block_offset(
        profiles, missing, camera_offset, options.search_range_m
    )
    return offset


def _percentile_inf(values: list[float], q: float) -> float:
    """The q-th percentile (linear, as numpy's) of values that may be
    infinite: infinite where it would interpolate towards an infinite one;
    NaN values are left out."""
    v = np.sort(np.asarray(values, float))
    v = v[~np.isnan(v)]
    if v.size == 0:
        return math.nan
    pos = q / 100.0 * (v.size - 1)
    i = int(math.floor(pos))
    frac = pos - i
    if frac == 0.0 or i + 1 >= v.size:
        return float(v[i])
    if math.isinf(v[i + 1]):
        return math.inf
    return float(v[i] + frac * (v[i + 1] - v[i]))


def _nanstat(values: list[float], fn) -> float:
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    return float(fn(v)) if v.size else math.nan


def evaluate_block(
    est: Block,
    gt: Block,
    corners_world: np.ndarray,
    visible: dict[str, np.ndarray | list[int]],
    options: EvaluateOptions | None = None,
) -> Evaluation:
    """Measure an estimated block against the true one; pure, no files.

    Images are matched by name.

    Parameters
    ----------
    est : Block, the estimated cameras and poses, ABSOLUTE frame.
    gt : Block, the true cameras and poses, ABSOLUTE frame.
    corners_world : (K, 3) array, true 3D building corners, absolute, metres.
    visible : dict image name -> (M,) int array-like of indices into
        ``corners_world``, the corners visible in the TRUE camera. Images not
        in the dict have no visible corner.
    options : EvaluateOptions, defaults if None.

    Returns
    -------
    Evaluation

    Raises
    ------
    ValueError
        Bad shapes, corner indices out of range, no image in common.
    """
    options = options or EvaluateOptions()
    corners_world = np.asarray(corners_world, float)
    if corners_world.ndim != 2 or corners_world.shape[1] != 3:
        raise ValueError(
            f"corners_world must be (K, 3), got shape {corners_world.shape}"
        )
    visible_idx = _visible_indices(visible, len(corners_world))
    gt_by_name = {im.name: im for im in gt.images.values()}
    est_by_name = {im.name: im for im in est.images.values()}
    common = sorted(set(gt_by_name) & set(est_by_name))
    extra = sorted(set(est_by_name) - set(gt_by_name))
    if not common:
        raise ValueError(
            "the estimated and the true block have no image name in common"
        )

    # 1. Work in a frame near the block: absolute UTM coordinates (~5e6 m)
    #    would cost ~1e-9 m of precision in every difference.
    ref = np.round(
        np.mean([gt_by_name[n].cam_from_world.center for n in common], axis=0)
    )
    corners_local = corners_world - ref

    # 2. One vertical offset for the whole model
    #    (EvaluateOptions.vertical_offset).
    est_ref = est.shifted(ref)
    gt_local = gt.shifted(ref)
    camera_offset = float(
        np.median(
            [
                est_by_name[n].cam_from_world.center[2]
                - gt_by_name[n].cam_from_world.center[2]
                for n in common
            ]
        )
    )
    offset = _block_offset(
        est_ref,
        gt_local,
        est_by_name,
        gt_by_name,
        corners_local,
        visible_idx,
        camera_offset,
        common,
        options,
    )
    # X_new = X_old - shift: the estimated cameras, lowered by the offset, in
    # the same local frame as the true ones.
    est_local = est_ref.shifted(np.array([0.0, 0.0, offset]))
    est_local_by_name = {im.name: im for im in est_local.images.values()}
    gt_local_by_name = {im.name: im for im in gt_local.images.values()}

    # 3. Rotation and centre errors, all matched images at once.
    errors = _pose_errors(est_local_by_name, gt_local_by_name, common)

    # 4. Corner deviations, image by image (vectorised over corners).
    results = [
        _image_evaluation(
            name,
            visible_idx.get(name, np.zeros(0, int)),
            errors,
            est_local,
            gt_local,
            est_local_by_name,
            gt_local_by_name,
            corners_local,
            options,
        )
        for name in sorted(gt_by_name)
    ]
    summary = _summary(results, len(extra), offset, camera_offset)
    logger.info(
        "registered %d / %d images "
        "(median deviation %.3g px%s, vertical offset %.3f m, %s)",
        summary.num_registered,
        summary.num_total,
        summary.deviation_median_px,
        " across verticals" if options.across_vertical else "",
        offset,
        offset_label(options),
    )
    if extra:
        logger.warning(
            "%d result image(s) not in the ground truth, ignored: %s",
            len(extra),
            ", ".join(extra[:5]) + (" ..." if len(extra) > 5 else ""),
        )
    return Evaluation(results, summary, options, extra)


def _visible_indices(
    visible: dict[str, np.ndarray | list[int]], num_corners: int
) -> dict[str, np.ndarray]:
    """Each image's visible corner indices as an (M,) int array, checked."""
    visible_idx: dict[str, np.ndarray] = {}
    for name, idx in visible.items():
        idx = np.asarray(idx, dtype=int).reshape(-1)
        if idx.size and (idx.min() < 0 or idx.max() >= num_corners):
            raise ValueError(
                f"visible corners of {name}: indices must be in "
                f"[0, {num_corners}), got [{idx.min()}, {idx.max()}]"
            )
        visible_idx[name] = idx
    return visible_idx


def _block_offset(
    est_ref: Block,
    gt_local: Block,
    est_by_name: dict,
    gt_by_name: dict,
    corners_local: np.ndarray,
    visible_idx: dict[str, np.ndarray],
    camera_offset: float,
    common: list[str],
    options: EvaluateOptions,
) -> float:
    """The block's one vertical offset (m): searched, the median of the
    images' own, or 0 when it is kept."""
    if options.remove_vertical_offset and options.vertical_offset == "search":
        return _searched_offset(
            est_ref,
            gt_local,
            est_by_name,
            gt_by_name,
            corners_local,
            visible_idx,
            camera_offset,
            options,
        )
    if options.remove_vertical_offset:
        return float(
            np.median(
                [
                    _image_offset(
                        est_ref,
                        gt_local,
                        est_by_name[n].image_id,
                        gt_by_name[n].image_id,
                        corners_local[visible_idx.get(n, np.zeros(0, int))],
                        options.vertical_offset,
                    )
                    for n in common
                ]
            )
        )
    return 0.0


def _pose_errors(
    est_by_name: dict, gt_by_name: dict, common: list[str]
) -> dict[str, tuple[float, float, float, float]]:
    """Per image: rotation error (deg), centre error, its horizontal part and
    its vertical component (m), the block's offset already removed."""
    R_est = np.stack([est_by_name[n].cam_from_world.rotation for n in common])
    R_true = np.stack([gt_by_name[n].cam_from_world.rotation for n in common])
    rot_err = rotation_angle_deg(R_est, R_true)  # (N,)
    c_est = np.stack([est_by_name[n].cam_from_world.center for n in common])
    c_true = np.stack([gt_by_name[n].cam_from_world.center for n in common])
    dc = c_est - c_true  # (N, 3), offset removed
    return {
        n: (
            float(rot_err[i]),
            float(np.linalg.norm(dc[i])),
            float(np.linalg.norm(dc[i, :2])),
            float(dc[i, 2]),
        )
        for i, n in enumerate(common)
    }


def _image_evaluation(
    name: str,
    idx: np.ndarray,
    errors: dict[str, tuple[float, float, float, float]],
    est_local: Block,
    gt_local: Block,
    est_local_by_name: dict,
    gt_local_by_name: dict,
    corners_local: np.ndarray,
    options: EvaluateOptions,
) -> ImageEvaluation:
    """One true image: its pose errors and the deviations of its ``idx``
    visible corners, or why it has none."""
    if idx.size == 0:
        ev = ImageEvaluation(name, STATUS_NO_CORNERS)
        if name in errors:
            (
                ev.rotation_error_deg,
                ev.center_error_m,
                ev.horizontal_error_m,
                ev.vertical_error_m,
            ) = errors[name]
        return ev
    if name not in errors:
        return ImageEvaluation(name, STATUS_MISSING, num_corners=int(idx.size))
    est_im, gt_im = est_local_by_name[name], gt_local_by_name[name]
    dev, behind = corner_deviations_px(
        est_local.cameras[est_im.camera_id],
        est_im.cam_from_world,
        gt_local.cameras[gt_im.camera_id],
        gt_im.cam_from_world,
        corners_local[idx],
        across_vertical=options.across_vertical,
    )
    unmeasurable = ~np.isfinite(dev) & ~behind
    if unmeasurable.any():
        # A "visible" corner behind the TRUE camera: bad ground truth.
        logger.warning(
            "%s: %d visible corner(s) do not project into the true camera; ignored",
            name,
            int(unmeasurable.sum()),
        )
    front = np.isfinite(dev)
    mean_dev = float(dev[front].mean()) if front.any() else math.nan
    max_dev = float(dev[front].max()) if front.any() else math.nan
    n_behind = int(behind.sum())
    if n_behind:
        status = STATUS_BEHIND
    elif mean_dev < options.registered_threshold_px:
        status = STATUS_REGISTERED
    else:
        status = STATUS_FAILED
    rot, cen, hor, ver = errors[name]
    return ImageEvaluation(
        name, status, rot, cen, hor, ver, mean_dev, max_dev, int(idx.size), n_behind
    )


def _summary(
    results: list[ImageEvaluation],
    num_extra: int,
    offset: float,
    camera_offset: float,
) -> EvaluationSummary:
    """The block's counts and medians over its images' evaluations."""
    measured = [r for r in results if r.status != STATUS_NO_CORNERS]
    present = [r for r in results if r.status != STATUS_MISSING]
    count = {
        s: sum(r.status == s for r in results)
        for s in (
            STATUS_REGISTERED,
            STATUS_FAILED,
            STATUS_BEHIND,
            STATUS_MISSING,
            STATUS_NO_CORNERS,
        )
    }
    means = [r.mean_deviation_px for r in measured]
    # Missing and behind: infinite (failures that the median must count).
    means_all = [
        r.mean_deviation_px
        if r.status in (STATUS_REGISTERED, STATUS_FAILED)
        else math.inf
        for r in measured
    ]
    return EvaluationSummary(
        num_total=len(measured),
        num_registered=count[STATUS_REGISTERED],
        num_failed=count[STATUS_FAILED],
        num_behind=count[STATUS_BEHIND],
        num_missing=count[STATUS_MISSING],
        num_no_corners=count[STATUS_NO_CORNERS],
        num_extra=num_extra,
        vertical_offset_m=offset,
        deviation_median_px=_nanstat(means, np.median),
        deviation_p95_px=_nanstat(means, lambda v: np.percentile(v, 95)),
        deviation_max_px=_nanstat(means, np.max),
        rotation_error_median_deg=_nanstat(
            [r.rotation_error_deg for r in present], np.median
        ),
        center_error_median_m=_nanstat([r.center_error_m for r in present], np.median),
        horizontal_error_median_m=_nanstat(
            [r.horizontal_error_m for r in present], np.median
        ),
        vertical_error_median_m=_nanstat(
            [abs(r.vertical_error_m) for r in present], np.median
        ),
        camera_offset_m=camera_offset,
        deviation_median_all_px=_percentile_inf(means_all, 50.0),
        deviation_p95_all_px=_percentile_inf(means_all, 95.0),
    )
