"""The per-image work that runs in worker processes (stages 1-2 of one
image, its re-registrations, the heads' focal jobs, the overlays).

Every function here takes one picklable argument (an :class:`ImageTask` or a
tuple) and reads the cadastre each worker loaded once
(:func:`worker_pool`). Failures come back as values.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from obliq_colmap.cadastre import Cadastre, CadastreOptions, load_cadastre
from obliq_colmap.geometry import Camera, Pose, rotation_aligning, rotation_z
from obliq_colmap.images import read_image
from obliq_colmap.lines import RefineOptions, refine_segments
from obliq_colmap.parallel import WorkerPool, image_seed
from obliq_colmap.registration import (
    RegistrationOptions,
    RegistrationResult,
    chance_test,
    draw_registration_overlay,
    focal_profile,
    refine_with_camera,
    register_image,
)
from obliq_colmap.state import ImageOutcome
from obliq_colmap.vanishing import VanishingOptions, VPPrior, detect_vertical_vp

__all__ = [
    "ImageTask",
    "chance_checked",
    "draw_overlay",
    "initial_image",
    "overlay_name",
    "profile_job",
    "refine_job",
    "reregister",
    "reregister_options",
    "set_registration",
    "worker_pool",
]

#: Per-process state: the cadastre, loaded once per worker.
_STATE: dict[str, Any] = {}


@dataclass
class ImageTask:
    """One image's work in a run, as the workers take it: the image, its
    priors' camera and pose, and the options of stages 1-2."""

    image_id: int
    name: str
    path: Path
    camera: Camera
    prior: Pose  # local frame
    cone_deg: float
    vanishing: VanishingOptions
    registration: RegistrationOptions
    #: Sub-pixel refit of the facade segments (None: LSD's as they are).
    refine: RefineOptions | None = None
    #: COLMAP model of the result: stage 2 refines the intrinsics in it.
    model: str = ""
    #: Intrinsics stage 2 starts from (result model), None: the priors'.
    start: Camera | None = None
    #: The prior has a position only: stage 1 with the aerial prior, stage 2
    #: over headings every this many degrees (0: the prior's rotation).
    heading_step_deg: float = 0.0

    # An image's random streams must not depend on the worker (or machine)
    # that runs it, nor on the other images or their ids in the run: stage
    # 1's are seeded from its name mixed with the user's seed; stage 2's
    # RANSAC takes the user's seed itself, the same for every image.
    @property
    def seeded_vanishing(self) -> VanishingOptions:
        """Stage 1's options, seeded for this image (:func:`image_seed`)."""
        seed = image_seed(self.name, self.vanishing.seed)
        return dataclasses.replace(self.vanishing, seed=seed)

    @property
    def result_camera(self) -> Camera:
        """The priors' camera in the result model (added terms start at 0)."""
        return self.camera.with_model(self.model or self.camera.model)


def _registration_inputs(
    task: ImageTask, segments: np.ndarray, vertical: np.ndarray | None
) -> tuple[np.ndarray, np.ndarray | None, Camera, bool]:
    """(segments, vertical, camera, segments_undistorted) of stage 2 of one
    image as :func:`register_image` takes them: the segments undistorted with
    the priors' camera (as the vanishing stage gives them), or through
    ``task.start``'s raw pixels when it is set."""
    if task.start is None:
        return segments, vertical, task.result_camera, True
    raw = task.camera.distort_pixels(segments.reshape(-1, 2)).reshape(-1, 2, 2)
    if vertical is not None:
        # The detected quantity is the vanishing point's pixel: the same
        # pixel through the start camera's focal length.
        vertical = np.linalg.solve(task.start.K, task.camera.K @ vertical)
        vertical = vertical / np.linalg.norm(vertical)
    return raw, vertical, task.start, False


def _register(
    task: ImageTask,
    segments: np.ndarray,
    vertical: np.ndarray | None,
    options: RegistrationOptions,
) -> RegistrationResult:
    """Stage 2 of one image from its segments (undistorted with the priors'
    camera, as the vanishing stage gives them), from ``task.start`` if set.

    Another start lens sees the segments through the raw pixels, and their
    inliers come back in the priors' frame, which the bundle expects.
    """
    seg, vertical, camera, undistorted = _registration_inputs(task, segments, vertical)
    result = register_image(
        seg,
        vertical,
        camera,
        task.prior,
        _STATE["cadastre"],
        options,
        segments_undistorted=undistorted,
    )
    if task.start is not None:
        inl = result.inlier_segments_px.reshape(-1, 2)
        result.inlier_segments_px = task.camera.undistort_pixels(
            task.start.distort_pixels(inl)
        ).reshape(-1, 2, 2)
    return result


def _init_worker(
    cadastre_path: Path, options: CadastreOptions, origin: np.ndarray
) -> None:
    _STATE["cadastre"] = load_cadastre(cadastre_path, options, origin)


def initial_image(task: ImageTask) -> ImageOutcome:
    """Stage 1 and 2 of one image; failures come back as values."""
    t0 = time.perf_counter()
    out = ImageOutcome(task.image_id, task.name, status="failed")
    img, problem = read_image(task.path)
    if img is None:
        out.status, out.message = "unreadable", f"{task.path}: {problem}"
        return out
    if img.shape != (task.camera.height, task.camera.width):
        out.status = "unreadable"
        out.message = (
            f"image is {img.shape[1]}x{img.shape[0]} px but its camera "
            f"{task.camera.camera_id} is {task.camera.width}x{task.camera.height}"
        )
        return out
    out.time_s["read"] = time.perf_counter() - t0
    if task.heading_step_deg > 0:
        prior = VPPrior.aerial()
    else:
        prior = VPPrior.from_rotation(task.prior.rotation, task.cone_deg)
    vp = detect_vertical_vp(img, task.seeded_vanishing, task.camera, prior)
    out.vp_status = vp.status
    out.line_segments = vp.segments
    if task.refine is not None:
        # Only stage 3 reads these (the facade edges): refitted on the
        # full-resolution image, in the frame the vanishing stage gave them.
        t1 = time.perf_counter()
        out.line_segments = refine_segments(img, vp.segments, task.camera, task.refine)
        out.time_s["refine_segments"] = time.perf_counter() - t1
    out.time_s["vanishing"] = vp.time_s.get("total", math.nan)
    options = task.registration
    if vp.status == "ok" and vp.vertical_segments is not None:
        out.segments = vp.vertical_segments.endpoints
        if vp.vertical_segments_free is not None:
            out.segments_free = vp.vertical_segments_free.endpoints
        out.vertical_direction = vp.vertical_direction
        if vp.vp is not None and vp.covariance is not None:
            out.vp, out.vp_covariance = vp.vp.copy(), vp.covariance.copy()
    else:
        # A missing or doubtful VP: all first-pass segments, filtered by the
        # prior rotation's vertical (within its uncertainty), which the
        # registration then refines with the pose.
        out.segments = vp.segments.endpoints if len(vp.segments) else out.segments
        options = _fallback_options(options)
    t1 = time.perf_counter()
    if task.heading_step_deg > 0:
        result = _heading_search(task, out.segments, out.vertical_direction, options)
    else:
        result = _register(task, out.segments, out.vertical_direction, options)
    out.time_s["registration"] = time.perf_counter() - t1
    set_registration(out, result)
    out.time_s["total"] = time.perf_counter() - t0
    return out


def _heading_search(
    task: ImageTask,
    segments: np.ndarray,
    vertical: np.ndarray | None,
    options: RegistrationOptions,
) -> RegistrationResult:
    """Stage 2 from each heading of a grid when the prior has a position only.

    The VP gives the camera's vertical (tilt and roll); a rotation about the
    world's vertical keeps it, so the prior rotation of heading psi is
    ``R0 @ R_z(psi)`` with ``R0`` the smallest rotation taking the world's
    down to the observed one. Each start's search spans half a grid step
    either side (``search_sigmas`` prior sigmas); the result with the most
    inlier corners wins, and it must pass stage 2's chance test like any.
    """
    if vertical is None:
        return RegistrationResult(
            success=False,
            cam_from_world=task.prior,
            vertical_direction=np.array([0.0, 0.0, 1.0]),
            message="no vertical vanishing point: with a position-only prior the "
            "camera's tilt comes from it",
        )
    step = task.heading_step_deg
    R0 = rotation_aligning(np.array([0.0, 0.0, -1.0]), vertical)
    sigma = 0.6 * step / options.search_sigmas  # +-0.6 step: the starts overlap
    opts = dataclasses.replace(options, prior_rotation_sigma_deg=sigma)
    best = None
    for psi in np.radians(np.arange(0.0, 360.0, step)):
        prior = Pose.from_center(R0 @ rotation_z(psi), task.prior.center)
        result = _register(
            dataclasses.replace(task, prior=prior), segments, vertical, opts
        )
        if result.success and (best is None or result.num_inliers > best.num_inliers):
            best = result
    if best is None:
        return RegistrationResult(
            success=False,
            cam_from_world=task.prior,
            vertical_direction=vertical,
            message=f"no heading of {int(360 / step)} tried (every {step:g} deg) "
            "registers the image",
        )
    return best


def _fallback_options(options: RegistrationOptions) -> RegistrationOptions:
    """Registration options when the vertical comes from the prior rotation.

    Segments are then kept within 2 sigma of the prior's tilt of the line
    towards the predicted VP, not within the detected VP's tolerance.
    """
    tolerance = max(options.vp_tolerance_deg, 2.0 * options.prior_rotation_sigma_deg)
    return dataclasses.replace(options, vp_tolerance_deg=tolerance)


def set_registration(out: ImageOutcome, result: RegistrationResult) -> None:
    """``result`` becomes ``out``'s registration (replaced, never mutated);
    its camera, status and message follow."""
    out.registration = result
    out.camera = result.camera
    out.status = "registered" if result.success else "failed"
    out.message = "" if result.success else result.message


def reregister_options(
    task: ImageTask, vertical: np.ndarray | None, ground: float | None
) -> RegistrationOptions:
    """The task's registration options with a given ground height (None: its
    own search), those for a vertical from the prior when none was detected."""
    options = (
        task.registration
        if vertical is not None
        else _fallback_options(task.registration)
    )
    return dataclasses.replace(options, ground_height=ground)


def reregister(
    args: tuple[ImageTask, np.ndarray, np.ndarray | None, float | None],
) -> RegistrationResult:
    """Register one image again with a given ground height (None: its own)."""
    task, segments, vertical, ground = args
    return _register(task, segments, vertical, reregister_options(task, *args[2:]))


def chance_checked(
    args: tuple[
        ImageTask, np.ndarray, np.ndarray | None, float | None, RegistrationResult
    ],
) -> RegistrationResult:
    """The chance test (:func:`~obliq_colmap.registration.chance_test`) of a
    result of :func:`reregister` on the same first four arguments."""
    task, segments, vertical, ground, result = args
    seg, n, camera, undistorted = _registration_inputs(task, segments, vertical)
    return chance_test(
        result,
        seg,
        n,
        camera,
        task.prior,
        _STATE["cadastre"],
        reregister_options(task, vertical, ground),
        segments_undistorted=undistorted,
    )


def draw_overlay(args: tuple[ImageTask, RegistrationResult, Path]) -> None:
    """Write one image's registration overlay (PNG) into the folder given."""
    import cv2

    task, result, folder = args
    img, _ = read_image(task.path, color=True)
    if img is None:
        return
    drawn = draw_registration_overlay(
        img, _STATE["cadastre"], task.camera, task.prior, result
    )
    cv2.imwrite(str(folder / overlay_name(task.name)), drawn)


def overlay_name(image_name: str) -> str:
    """File name of an image's overlay: its name, folders flattened, as PNG."""
    return Path(image_name.replace("/", "__")).with_suffix(".png").name


def profile_job(
    args: tuple[RegistrationResult, Camera, np.ndarray, np.ndarray, Camera, Any],
) -> np.ndarray:
    """:func:`~obliq_colmap.registration.focal_profile` of one image (the
    heads' focal pass)."""
    result, camera, scales, segments, segments_camera, options = args
    return focal_profile(
        result, camera, scales, segments, segments_camera, _STATE["cadastre"], options
    )


def refine_job(
    args: tuple[RegistrationResult, Camera, np.ndarray, Camera, Any],
) -> RegistrationResult:
    """:func:`~obliq_colmap.registration.refine_with_camera` of one image
    (the heads' focal pass)."""
    result, camera, segments, segments_camera, options = args
    return refine_with_camera(
        result, camera, segments, segments_camera, _STATE["cadastre"], options
    )


def worker_pool(
    num_workers: int,
    init_args: tuple,
    cadastre: Cadastre,
    progress: bool,
    dask_scheduler: str | None = None,
) -> WorkerPool:
    """The pool of the per-image stages, local or on a Dask cluster
    (``dask_scheduler``: see :class:`~obliq_colmap.parallel.WorkerPool`);
    each worker loads the cadastre once (one local worker: the calling
    process uses the one already loaded)."""
    return WorkerPool(
        num_workers,
        _init_worker,
        init_args,
        local_initializer=lambda: _STATE.__setitem__("cadastre", cadastre),
        progress=progress,
        dask_scheduler=dask_scheduler,
    )
