"""The stage's entry (:func:`register_image`): the search, then the chance
test of a weak result against the same search with the segments mirrored;
and the ground height of a block from its confident registrations."""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import replace

import numpy as np

from obliq_colmap.geometry import Camera, Pose
from obliq_colmap.registration.options import RegistrationOptions, RegistrationResult
from obliq_colmap.registration.search import search
from obliq_colmap.registration.view import EZ


def register_image(
    segments_px: np.ndarray,
    vertical_direction_cam: np.ndarray | None,
    camera: Camera,
    prior: Pose,
    cadastre,
    options: RegistrationOptions | None = None,
    *,
    segments_undistorted: bool = False,
) -> RegistrationResult:
    """Register one image to the map from its vertical segments (stage 2).

    A pure function of its inputs (safe in a process pool); deterministic for
    ``options.seed``.

    Parameters
    ----------
    segments_px : (N, 2, 2) float array
        Vertical segments (endpoint k = (x, y) of segment i), COLMAP pixels
        as detected, i.e. DISTORTED (undistorted here with the camera) unless
        ``segments_undistorted``.
    vertical_direction_cam : (3,) array or None
        Unit vertical direction in the camera frame, pointing down the world,
        from the vanishing stage; None when its detection failed: the prior
        rotation's vertical is used and refined with the pose.
    camera : Camera
        Rough intrinsics (COLMAP model).
    prior : Pose
        Rough ``cam_from_world`` in the cadastre's LOCAL frame; its height is in
        an unknown vertical datum.
    cadastre : obliq_colmap.cadastre.Cadastre
    options : RegistrationOptions or None for the defaults.
    segments_undistorted : bool
        The segments are already in pixels of the pinhole part ``K`` (the
        vanishing stage's second-pass segments are).

    Returns
    -------
    RegistrationResult
        ``success`` False with a message on failure (nothing is raised for a
        failed registration).

    Raises
    ------
    ValueError
        Malformed inputs (shapes, non-finite vertical direction).
    """
    options = options or RegistrationOptions()
    args = (segments_px, vertical_direction_cam, camera, prior, cadastre, options)
    result = search(*args, segments_undistorted)
    return chance_test(result, *args, segments_undistorted=segments_undistorted)


def chance_test(
    result: RegistrationResult,
    segments_px: np.ndarray,
    vertical_direction_cam: np.ndarray | None,
    camera: Camera,
    prior: Pose,
    cadastre,
    options: RegistrationOptions,
    *,
    segments_undistorted: bool = False,
) -> RegistrationResult:
    """``result`` (of :func:`register_image` on these arguments, with or
    without the test) refused as a failure when its inlier count is no more
    than ``options.chance_factor`` x what chance gives (:func:`chance_counts`);
    results with ``options.chance_test_below`` inliers or more pass untested.
    """
    if (
        options.chance_trials == 0
        or not result.success
        or result.num_inliers >= options.chance_test_below
        or result.chance_inliers >= 0
    ):
        return result
    t0 = time.perf_counter()
    args = (segments_px, vertical_direction_cam, camera, prior, cadastre, options)
    chance = max(chance_counts(*args, segments_undistorted))
    timings = dict(result.timings)
    timings["chance"] = time.perf_counter() - t0
    timings["total"] = timings.get("total", 0.0) + timings["chance"]
    result = dataclasses.replace(result, chance_inliers=chance, timings=timings)
    if result.num_inliers > options.chance_factor * chance:
        return result
    return dataclasses.replace(
        result,
        success=False,
        cam_from_world=prior,
        camera=None,
        message=(
            f"no consensus: {result.num_inliers} inlier corners is no more than "
            f"chance (the same search with the segments mirrored finds up to "
            f"{chance}; need more than {options.chance_factor:g} x that)"
        ),
    )


def _mirrored(segments: np.ndarray, vp: np.ndarray, point: np.ndarray) -> np.ndarray:
    """(N, 2, 2) segments reflected about the image line through the vertical
    VP ``vp`` (3,) (homogeneous, may lie at infinity) and the pixel ``point``
    (2,): lines through the VP stay lines through it."""
    u = vp[:2] - point * vp[2]
    u = u / np.linalg.norm(u)
    reflect = 2.0 * np.outer(u, u) - np.eye(2)
    return (segments - point) @ reflect.T + point


def chance_counts(
    segments_px: np.ndarray,
    vertical_direction_cam: np.ndarray | None,
    camera: Camera,
    prior: Pose,
    cadastre,
    options: RegistrationOptions,
    segments_undistorted: bool = False,
) -> list[int]:
    """Inlier corners the same search finds with the segments mirrored (one
    count per mirror, ``options.chance_trials`` of them): what chance alone
    gives this image's segments against this map.

    The mirror axes pass through the vertical VP and points on the image's
    middle row spread by an eighth of the width around the principal point.
    A mirror about the axis through the principal point is the image of the
    map mirrored about the camera's vertical plane: the same corners at the
    same distances in view, the same segments, but no relation between them.
    Arguments as :func:`register_image`. Each mirror is one more search.
    """
    seg = np.asarray(segments_px, float).reshape(-1, 2, 2)
    if camera.has_distortion and not segments_undistorted and len(seg):
        seg = camera.undistort_pixels(seg.reshape(-1, 2)).reshape(-1, 2, 2)
    n = vertical_direction_cam
    down = n if n is not None else prior.rotation @ -EZ
    vp = camera.K @ np.asarray(down, float)
    null = replace(options, min_inliers=3, chance_trials=0)
    m = options.chance_trials
    counts = []
    for k in range(m):
        shift = (k - (m - 1) / 2.0) * camera.width / 8.0
        point = np.array([camera.K[0, 2] + shift, camera.K[1, 2]])
        r = search(_mirrored(seg, vp, point), n, camera, prior, cadastre, null, True)
        counts.append(r.num_inliers)
    return counts


def block_ground_height(
    results: list[RegistrationResult], min_inliers: int = 20
) -> float | None:
    """The ground height of a block from its confident registrations.

    All priors of a block share one vertical datum, so the ground heights found
    per image agree up to the terrain and the prior height noise. A second
    pass of :func:`register_image` with ``options.ground_height`` set to this
    value rescues images whose own ground-height search failed (their
    results have few inliers).

    Parameters
    ----------
    results : registrations of the images of one block (local frame).
    min_inliers : only results with at least this many inlier corners count.

    Returns
    -------
    float, the median ground height (m), or None when no result qualifies.
    """
    heights = [
        r.ground_height
        for r in results
        if r.success and r.num_inliers >= min_inliers and math.isfinite(r.ground_height)
    ]
    return float(np.median(heights)) if heights else None
