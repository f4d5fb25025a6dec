"""Stage 3 in the run (:func:`block_stage`): the bundle
(:func:`obliq_colmap.adjustment.bundle_stage`), the check of the pose priors
(:func:`check_pose_priors`), the failed and weak images registered again
against the solved block (:func:`reregister_failed`) and the bundle solved
again with them (undone when it spoils the block, unless the images that two
registrations confirm outvote what it rejects), then the leave-outs (and,
on request, the images left out as wrong registered once more against the
block solved without them).
"""

from __future__ import annotations

import copy
import dataclasses
import logging
import math
import time
from collections.abc import Sequence

import numpy as np

from obliq_colmap.adjustment import Stage3, TiePoints, Verdicts, bundle_stage
from obliq_colmap.bundle import BundleResult
from obliq_colmap.errors import InputError
from obliq_colmap.geometry import (
    Camera,
    Pose,
    axis_angle_from_rotation,
    rotation_from_axis_angle,
)
from obliq_colmap.parallel import WorkerPool
from obliq_colmap.pipeline.options import PipelineOptions
from obliq_colmap.pipeline.resection import (
    MIN_INLIERS,
    block_tie_points,
    tie_resections,
)
from obliq_colmap.pipeline.verdicts import (
    block_verdicts,
    leave_out_rejected,
    unsupported_placements,
    warn_imprecise,
    warn_vp_disagreement,
)
from obliq_colmap.pipeline.workers import (
    ImageTask,
    reregister,
    set_registration,
    worker_pool,
)
from obliq_colmap.registration import RegistrationOptions, RegistrationResult
from obliq_colmap.state import BlockState, ImageOutcome, Inputs

__all__ = ["block_stage", "check_pose_priors", "reregister_failed"]

logger = logging.getLogger(__name__)


def block_stage(
    inputs: Inputs,
    tasks: list[ImageTask],
    outcomes: list[ImageOutcome],
    options: PipelineOptions,
    timings: dict[str, float],
    pool_args: tuple[int, tuple],
) -> tuple[BlockState, BundleResult | None, Stage3, list[str]]:
    """Stage 3 on the per-image outcomes, and what follows it.

    The bundle (:func:`~obliq_colmap.adjustment.bundle_stage`); the failed
    and weak images registered again against the solved block and, where that
    succeeds, the bundle solved again (:func:`reregister_failed`), unless
    that second bundle disagrees with an image the first accepted: then the
    first bundle's block is kept and the images registered again get their
    earlier outcome back (a failed one stays out; measured: `hard` s2 /
    seed 0, a wrong re-registration 24 px off pulled two images 17-21 px
    off). Images registered again that a second registration confirms (the
    first bundle's pose within ``reregistration_agreement_px``, or their tie
    points) and that outnumber the images rejected keep the new block, with
    the others dropped and the bundle solved once more where needed
    (:func:`_confirmed`); then the images the last bundle disagrees with or
    determines too poorly are left out (:func:`leave_out_rejected`). ``pool_args``:
    (workers, initializer arguments) of the re-registration's process pool.
    Outcomes are updated in place. Returns the block, the last bundle's
    result (None when it was skipped or failed), its facade stage and the
    names registered again.
    """
    by_id = {o.image_id: o for o in outcomes}
    state = BlockState.from_outcomes([o for o in outcomes if o.registered])
    ties = None
    if options.adjustment.tie_points and len(state.poses) >= 2:
        t0 = time.perf_counter()
        ties = block_tie_points(
            inputs, state, tasks, outcomes, options.adjustment.tie_point_options
        )
        timings["tie_points"] = time.perf_counter() - t0
    state, bundle_result, stage3 = bundle_stage(
        inputs, by_id, state, options.adjustment, timings, ties
    )
    reregistered: list[str] = []
    rejected, imprecise, misplaced = block_verdicts(stage3, options)
    check_pose_priors(inputs, by_id, len(state.poses), rejected, options)
    if options.reregister_failed and bundle_result is not None:
        t0 = time.perf_counter()
        workers, init_args = pool_args
        saved = {o.image_id: copy.copy(o) for o in outcomes}  # for an undo
        first = (state, bundle_result, stage3)
        with worker_pool(
            workers,
            init_args,
            inputs.cadastre,
            options.progress,
            options.dask_scheduler,
        ) as pool:
            joined, reregistered = reregister_failed(
                pool, tasks, outcomes, state, options, ties
            )
        state = joined
        timings["reregistration"] = time.perf_counter() - t0
        if reregistered:
            state, bundle_result, stage3, verdicts, reregistered = (
                _settle_second_bundle(
                    inputs,
                    by_id,
                    outcomes,
                    first,
                    joined,
                    reregistered,
                    saved,
                    (rejected, imprecise, misplaced),
                    options,
                    timings,
                    ties,
                )
            )
            rejected, imprecise, misplaced = verdicts
    held = set(state.poses)
    state = _leave_out(state, stage3, by_id, rejected, imprecise, misplaced)
    wrong = {i for i in [*rejected, *misplaced] if i in held - set(state.poses)}
    if options.reregister_rejected and bundle_result is not None and wrong:
        t0 = time.perf_counter()
        state, bundle_result, stage3, again = _register_left_out(
            inputs,
            tasks,
            outcomes,
            (state, bundle_result, stage3),
            wrong,
            options,
            timings,
            pool_args,
            ties,
        )
        timings["reregistration"] = (
            timings.get("reregistration", 0.0) + time.perf_counter() - t0
        )
        reregistered += again
    warn_imprecise(state, stage3, by_id, options.warn_predicted_sd_px)
    warn_vp_disagreement(state, stage3, by_id)
    return state, bundle_result, stage3, reregistered


def _settle_second_bundle(
    inputs: Inputs,
    by_id: dict[int, ImageOutcome],
    outcomes: list[ImageOutcome],
    first: tuple[BlockState, BundleResult | None, Stage3],
    joined: BlockState,
    reregistered: list[str],
    saved: dict[int, ImageOutcome],
    verdicts: Verdicts,
    options: PipelineOptions,
    timings: dict[str, float],
    ties: TiePoints | None,
) -> tuple[BlockState, BundleResult | None, Stage3, Verdicts, list[str]]:
    """The bundle solved again on ``joined``, the first block (``first``:
    state, result, stage 3) with the images ``reregistered`` (names); kept,
    kept with only the confirmed of them (:func:`_confirmed`), or undone
    for the first block with their earlier outcomes back (``saved``), as
    :func:`block_stage` says. ``verdicts``: the first bundle's. Returns the
    block, its bundle result, stage 3, verdicts and the names of the images
    registered again that it keeps."""
    rejected, imprecise, misplaced = verdicts
    state, bundle_result, stage3, verdicts = _solve_again(
        inputs, by_id, joined, options, timings, ties, reregistered
    )
    again, imprecise_again, misplaced_again = verdicts
    new = {o.image_id for o in outcomes if o.name in reregistered}
    # Spoiled: rejected now, accepted before. Not the precision
    # verdict: an image it flags is left out of the second block,
    # which measured better than going back to the first (`hard` s2
    # / seed 2: 34 / 36 at 0.64 px against 32 / 36 at 1.11 px); the
    # height verdict is treated alike.
    spoiled = sorted(set(again) - set(rejected) - new)
    # Images placed by their tie points AND registered to the map, or
    # registered again where the first bundle had them, are confirmed
    # twice: where they outnumber the images the bundle now rejects,
    # those were the wrong ones (a no_vp image written on a weak
    # pose; a head the new images pull to its right place), and the
    # new block stands. The others may be what spoiled it (`hard` s2:
    # an image re-registered 24 px off): without them, once more.
    confirmed = _confirmed(first[0], state, by_id, new, options)
    if spoiled and confirmed != new and len(confirmed) > len(spoiled):
        dropped = new - confirmed
        logger.info(
            "the bundle with the images registered again rejects %s:"
            " solved once more without those not confirmed (%s)",
            ", ".join(by_id[i].name for i in spoiled),
            ", ".join(by_id[i].name for i in sorted(dropped)),
        )
        third = _solve_with_confirmed(
            inputs,
            by_id,
            first[0],
            joined,
            saved,
            dropped,
            confirmed,
            options,
            timings,
            ties,
        )
        spoiled_now = sorted(set(third[3][0]) - set(rejected) - confirmed)
        # solved without the others, a confirmed image can leave the pose
        # that confirmed it: then neither of its registrations holds
        astray = _astray(first[0], third[0], confirmed, options)
        if len(spoiled_now) + len(astray) < len(confirmed):
            state, bundle_result, stage3, verdicts = third
            again, imprecise_again, misplaced_again = verdicts
            _note_unconfirmed(by_id, dropped, spoiled)
            state = _without_astray(state, by_id, astray)
            confirmed = confirmed - set(astray)
            reregistered = [by_id[i].name for i in sorted(confirmed)]
            new, spoiled = confirmed, spoiled_now
    if spoiled and confirmed == new and len(spoiled) < len(new):
        logger.warning(
            "the bundle with the images registered again and confirmed"
            " (%s) rejects %s, accepted before: they are left out",
            ", ".join(by_id[i].name for i in sorted(new)),
            ", ".join(by_id[i].name for i in spoiled),
        )
        rejected, imprecise = again, imprecise_again
        misplaced = misplaced_again
    elif spoiled:
        # The second bundle disagrees with images the first accepted:
        # the images registered again pulled the block off (a wrong
        # pose with enough inliers). Back to the first bundle.
        names = ", ".join(by_id[i].name for i in spoiled)
        for i in new:
            o = by_id[i]
            _restore(o, saved[i])
            o.message = (
                "registered against the solved block, but the bundle"
                f" with it disagreed with {names}: left out"
            )
            if o.registered:
                # Two registrations of a weak image that the block
                # cannot both hold: the first may be the wrong one
                # (high-rise seed 1: N_20 kept 4.9 px off, its
                # predicted sd below 1 px).
                o.message = (
                    "written with a warning: registered against the"
                    " solved block, the bundle with that pose disagreed"
                    f" with {names}; its first pose"
                    f" ({o.registration.num_inliers} inlier corners) is"
                    " kept and may be more than 2 px off"
                )
            logger.warning("%s: %s", o.name, o.message)
        state, bundle_result, stage3 = first
        reregistered = []
    else:
        rejected, imprecise = again, imprecise_again
        misplaced = misplaced_again
    return state, bundle_result, stage3, (rejected, imprecise, misplaced), reregistered


def check_pose_priors(
    inputs: Inputs,
    by_id: dict[int, ImageOutcome],
    num_images: int,
    rejected: list[int],
    options: PipelineOptions,
) -> None:
    """Raise an input error when the bundle's pose priors, not the images,
    are what it disagrees with (:attr:`PipelineOptions.max_prior_rejected_fraction`).

    Parameters
    ----------
    num_images : images in the bundle that ``rejected`` (ids) came from.

    Raises
    ------
    InputError
        Naming the priors model, the sigmas given and how far the block solved
        without them lies from them.
    """
    b = options.adjustment.bundle
    given = []
    if b.position_prior_sigma_m is not None:
        given.append(f"--bundle_position_sigma {b.position_prior_sigma_m:g} m")
    if b.rotation_prior_sigma_deg is not None:
        given.append(f"--bundle_rotation_sigma {b.rotation_prior_sigma_deg:g} deg")
    limit = options.max_prior_rejected_fraction
    if not given or limit <= 0 or len(rejected) <= limit * num_images:
        return
    free = dataclasses.replace(
        options.adjustment,
        bundle=dataclasses.replace(
            b, position_prior_sigma_m=None, rotation_prior_sigma_deg=None
        ),
    )
    state = BlockState.from_outcomes([o for o in by_id.values() if o.registered])
    _, result, stage3 = bundle_stage(inputs, by_id, state, free, {})
    if result is None:
        return
    rejected_free = block_verdicts(stage3, options)[0]
    logger.info(
        "the bundle disagrees with %d of %d images with the pose priors, with"
        " %d without them",
        len(rejected),
        num_images,
        len(rejected_free),
    )
    if 2 * len(rejected_free) > len(rejected):
        return  # the images disagree either way: not the priors
    ids = [i for i in result.poses if i not in rejected_free]
    solved = np.array([result.poses[i].center for i in ids])
    prior = np.array([inputs.priors.images[i].cam_from_world.center for i in ids])
    d = solved - prior
    d -= np.median(d, axis=0)  # the frames' offset and the vertical datum
    # Angle of R R_prior^T: acos((trace - 1) / 2).
    tr = [
        np.trace(
            result.poses[i].rotation @ inputs.priors.images[i].cam_from_world.rotation.T
        )
        for i in ids
    ]
    angle = np.degrees(np.arccos(np.clip((np.array(tr) - 1.0) / 2.0, -1.0, 1.0)))
    raise InputError(
        inputs.priors_path,
        f"the priors' poses are less accurate than {' and '.join(given)}: with"
        f" them the bundle disagrees with {len(rejected)} of {num_images}"
        f" images, without them with {len(rejected_free)}; solved without them,"
        " the camera centres lie a median"
        f" {np.median(np.linalg.norm(d[:, :2], axis=1)):.2f} m horizontally and"
        f" {np.median(np.abs(d[:, 2])):.2f} m vertically (after a common offset)"
        f" and the rotations {np.median(angle):.3f} deg from the priors. Give"
        " their real accuracy, or leave the option out",
    )


def reregister_failed(
    pool: WorkerPool,
    tasks: list[ImageTask],
    outcomes: list[ImageOutcome],
    state: BlockState,
    options: PipelineOptions,
    ties: TiePoints | None = None,
    only: set[int] | None = None,
) -> tuple[BlockState, list[str]]:
    """Register failed and weak images again, against the solved block.

    What the solved block knows that one image's priors do not: the
    intrinsics of the image's head (the priors' focal may be percents off,
    which a weak image cannot resolve by itself), the ground height around
    the image, and the systematic part of its head's prior errors (the median
    correction of the head's confident images, where it is significant).
    Each image that failed per image, or registered with fewer than
    ``options.rescue_min_inliers`` inlier corners, is registered once more
    with these and its head's camera held; the new result is kept when it
    succeeds with more inliers than before (the caller then solves the
    bundle again). With ``ties``, an image that its tie points place in the
    block (:func:`~obliq_colmap.pipeline.resection.tie_resections`) starts
    from that pose instead, with tight prior sigmas and the vertical it
    gives (:data:`TIE_START_SIGMAS`), whether its head has confident images
    or not; with ``options.reregister_placed`` so does every other image its
    tie points place. ``only``: these image ids instead of the failed and
    weak ones (and no others).

    Returns
    -------
    The block with the new registrations (per-image poses, their head's
    camera) and the names of the images concerned.
    """
    by_id = {o.image_id: o for o in outcomes}
    head_of = {t.image_id: t.camera.camera_id for t in tasks}

    def weak(o: ImageOutcome) -> bool:
        return (
            not o.registered or o.registration.num_inliers < options.rescue_min_inliers
        )

    def chosen(o: ImageOutcome) -> bool:
        return weak(o) if only is None else o.image_id in only

    def placed(o: ImageOutcome) -> bool:  # tried where its tie points place it
        return chosen(o) or (only is None and options.reregister_placed)

    confident = [i for i in state.poses if by_id[i].registered and not weak(by_id[i])]
    head_camera = {head_of[i]: state.cameras[i] for i in state.poses}
    task_of = {t.image_id: t for t in tasks}
    # A head with no image in the block (the nadir camera of a five-camera
    # system: stage 2 cannot register a nadir view to the map's corners) is
    # placed by its tie points alone, from its priors' camera.
    camera_of = {
        o.image_id: head_camera.get(
            head_of[o.image_id],
            task_of[o.image_id].start or task_of[o.image_id].camera,
        )
        for o in outcomes
    }
    starts = {}
    if ties is not None:
        candidates = {
            o.image_id: camera_of[o.image_id]
            for o in outcomes
            if o.registration is not None and placed(o)
        }
        new_head = frozenset(i for i in candidates if head_of[i] not in head_camera)
        starts = tie_resections(state, ties, candidates, new_head)
    todo = [
        k
        for k, o in enumerate(outcomes)
        if o.registration is not None
        and len(o.segments) >= options.registration.min_segments
        and (
            (placed(o) and o.image_id in starts)
            or (
                chosen(o)
                and any(head_of[i] == tasks[k].camera.camera_id for i in confident)
            )
        )
    ]
    if not todo:
        return state, []
    heads: dict[int, list[ImageTask]] = {}
    for i in confident:
        heads.setdefault(head_of[i], []).append(task_of[i])
    offsets = _head_offsets(state, heads)
    ground0 = float(np.median([p[2] for p in state.planes.values()]))
    jobs = []
    for k in todo:
        cid = tasks[k].camera.camera_id
        vertical = outcomes[k].vertical_direction
        if tasks[k].image_id in starts:
            task = _tie_task(
                tasks[k],
                camera_of[tasks[k].image_id],
                starts[tasks[k].image_id],
                options,
                solved_camera=cid in head_camera,
            )
            vertical = None  # the start's, far better than a missed VP's
        else:
            camera = state.cameras[heads[cid][0].image_id]
            task = _head_task(tasks[k], camera, offsets[cid], options.registration)
        ground = _block_ground_at(state, _footprint_xy(task.prior, ground0))
        jobs.append((task, outcomes[k].segments, vertical, ground))
    logger.info(
        "%d failed or weak image(s) registered again against the solved block",
        len(jobs),
    )
    tries = pool.map(reregister, jobs, "against the block")
    poses, cameras = dict(state.poses), dict(state.cameras)
    planes = {i: p.copy() for i, p in state.planes.items()}
    names, new = [], set()
    for k, job, result in zip(todo, jobs, tries, strict=True):
        o = outcomes[k]
        before = o.registration.num_inliers if o.registered else -1
        if not result.success and o.image_id in starts and not o.registered:
            # Its tie points place it in the block; the map alone cannot
            # (few building corners with vertical edges): it joins the
            # bundle with its tie and facade rows.
            result = _placed_by_ties(job[0], starts[o.image_id], job[3], result)
        if not result.success or result.num_inliers <= before:
            if not o.registered:
                o.message += f"; against the solved block: {result.message}"
            continue
        set_registration(o, result)
        o.reregistered = True
        o.placed_by_ties = o.image_id in starts
        if result.vertical_source == "tie points":
            o.message = result.message  # registered, but not by the map
        poses[o.image_id] = result.cam_from_world
        cameras[o.image_id] = job[0].start
        planes[o.image_id] = result.height_plane.copy()
        names.append(o.name)
        new.add(o.image_id)
    # The new poses are per-image registrations: the next bundle corrects
    # their datum against the solved images.
    solved = state.solved - new
    return BlockState(poses, cameras, planes, state.shared, solved), names


def _solve_again(
    inputs: Inputs,
    by_id: dict[int, ImageOutcome],
    state: BlockState,
    options: PipelineOptions,
    timings: dict[str, float],
    ties: TiePoints | None,
    joined: Sequence[str],
) -> tuple[BlockState, BundleResult | None, Stage3, Verdicts]:
    """The bundle solved again on ``state``, which the images ``joined``
    (by name) joined registered against the solved block (its time added
    to the earlier solves'), and its verdicts (:func:`block_verdicts`)."""
    logger.info(
        "%d image(s) registered against the solved block (%s): "
        "the bundle is solved again",
        len(joined),
        ", ".join(joined),
    )
    before = timings["bundle"]
    state, result, stage3 = bundle_stage(
        inputs, by_id, state, options.adjustment, timings, ties
    )
    timings["bundle"] += before
    return state, result, stage3, block_verdicts(stage3, options)


def footprint_shift_px(before: BlockState, after: BlockState, image_id: int) -> float:
    """Mean displacement (px) of an image's ground footprint from its pose
    and camera in ``before`` to those in ``after``: a 5 x 5 grid of its
    pixels cast onto its ground plane in ``before``, projected in ``after``."""
    cam0, cam1 = before.cameras[image_id], after.cameras[image_id]
    u, v = np.meshgrid(np.linspace(0.1, 0.9, 5), np.linspace(0.1, 0.9, 5))
    px = np.column_stack([u.ravel() * cam0.width, v.ravel() * cam0.height])
    pose = before.poses[image_id]
    rays = np.column_stack([cam0.cam_from_img(px), np.ones(len(px))])
    d = rays @ pose.rotation  # world directions (R^T ray)
    c = pose.center
    a, b, z0 = before.planes[image_id]  # z = a x + b y + z0
    t = (a * c[0] + b * c[1] + z0 - c[2]) / (d[:, 2] - a * d[:, 0] - b * d[:, 1])
    X = c + t[:, None] * d
    q = cam1.img_from_cam(after.poses[image_id].transform(X))
    return float(np.mean(np.linalg.norm(q - px, axis=1)))


def _confirmed(
    first: BlockState,
    second: BlockState,
    by_id: dict[int, ImageOutcome],
    new: set[int],
    options: PipelineOptions,
) -> set[int]:
    """The images registered again (``new``) that two registrations place:
    the bundle solved again within ``options.reregistration_agreement_px``
    of where the first had them or, for an image the first did not have,
    its tie points as well as the map."""
    shift = {
        i: footprint_shift_px(first, second, i)
        for i in new
        if i in first.poses and i in second.poses
    }
    logger.info(
        "images registered again, shift from the first bundle's pose: %s",
        ", ".join(
            f"{by_id[i].name} {shift[i]:.1f} px" if i in shift else by_id[i].name
            for i in sorted(new)
        ),
    )
    # A tie placement is a second registration only of an image the first
    # bundle did not have: one it had and now sits far from was started
    # from its ties and moved (our high-rise s3: W_20, S_22 16-19 px off).
    limit = options.reregistration_agreement_px
    return {
        i
        for i in new
        if shift.get(i, math.inf) <= limit
        or (by_id[i].placed_by_ties and i not in shift)
    }


def _astray(
    first: BlockState, block: BlockState, images: set[int], options: PipelineOptions
) -> dict[int, float]:
    """The ``images`` that ``block`` places more than
    ``options.reregistration_agreement_px`` from where ``first`` had them,
    with their footprint shift (px)."""
    shifts = {
        i: footprint_shift_px(first, block, i)
        for i in images
        if i in first.poses and i in block.poses
    }
    return {i: v for i, v in shifts.items() if v > options.reregistration_agreement_px}


def _without_astray(
    state: BlockState, by_id: dict[int, ImageOutcome], astray: dict[int, float]
) -> BlockState:
    """The block without the ``astray`` images (:func:`_astray`), each named
    with its shift."""
    for i, shift in astray.items():
        o = by_id[i]
        o.status = "failed"
        o.message = (
            "left out: registered against the solved block where the first"
            f" bundle had it, but the bundle solved again moved it {shift:.1f}"
            " px from there (neither pose holds)"
        )
        logger.warning("%s: %s", o.name, o.message)
    return state.without(astray)


def _note_unconfirmed(
    by_id: dict[int, ImageOutcome], dropped: set[int], spoiled: Sequence[int]
) -> None:
    """Say on each image registered again but not kept why: unconfirmed,
    and the bundle with it rejected images the first accepted."""
    names = ", ".join(by_id[j].name for j in spoiled)
    for i in sorted(dropped):
        o = by_id[i]
        o.message = (
            "registered against the solved block, but neither its tie points"
            " nor its first pose confirm it and the bundle with it disagreed"
            f" with {names}: "
            + (
                "its first pose is kept and may be more than 2 px off"
                if o.registered
                else "left out"
            )
        )
        logger.warning("%s: %s", o.name, o.message)


def _solve_with_confirmed(
    inputs: Inputs,
    by_id: dict[int, ImageOutcome],
    first: BlockState,
    joined: BlockState,
    saved: dict[int, ImageOutcome],
    dropped: set[int],
    confirmed: set[int],
    options: PipelineOptions,
    timings: dict[str, float],
    ties: TiePoints | None,
) -> tuple[BlockState, BundleResult | None, Stage3, Verdicts]:
    """The bundle solved once more on ``joined`` (the first block with every
    image registered again) with only the ``confirmed`` of those; the
    ``dropped`` ones back to their earlier outcome (from ``saved``) and,
    where the first block had them, its pose."""
    poses, cameras = dict(joined.poses), dict(joined.cameras)
    planes = dict(joined.planes)
    for i in dropped:
        _restore(by_id[i], saved[i])
        for part, earlier in (
            (poses, first.poses),
            (cameras, first.cameras),
            (planes, first.planes),
        ):
            part.pop(i, None)
            if i in earlier:
                part[i] = earlier[i]
    solved = joined.solved | (frozenset(dropped) & first.solved)
    state = BlockState(poses, cameras, planes, joined.shared, solved)
    names = [by_id[i].name for i in sorted(confirmed)]
    return _solve_again(inputs, by_id, state, options, timings, ties, names)


def _leave_out(
    state: BlockState,
    stage3: Stage3,
    by_id: dict[int, ImageOutcome],
    rejected: Sequence[int],
    imprecise: Sequence[int],
    misplaced: Sequence[int],
) -> BlockState:
    """The block without the images the bundle's verdicts leave out
    (:func:`~obliq_colmap.pipeline.verdicts.leave_out_rejected`)."""
    # An image placed by its tie points alone has no map corner of its own:
    # its facade rows, matched from that pose, are the weak part, and the
    # share of them the bundle rejects does not judge its pose, which its
    # tie rows hold.
    rejected = [
        i
        for i in rejected
        if not (by_id[i].placed_by_ties and by_id[i].registration.num_inliers == 0)
    ]
    unsupported = unsupported_placements(state, stage3, by_id, MIN_INLIERS)
    return leave_out_rejected(
        state, stage3, by_id, rejected, imprecise, misplaced, unsupported
    )


def _register_left_out(
    inputs: Inputs,
    tasks: list[ImageTask],
    outcomes: list[ImageOutcome],
    block: tuple[BlockState, BundleResult, Stage3],
    left_out: set[int],
    options: PipelineOptions,
    timings: dict[str, float],
    pool_args: tuple[int, tuple],
    ties: TiePoints | None,
) -> tuple[BlockState, BundleResult, Stage3, list[str]]:
    """The images the bundle left out as wrong (``left_out``: too many of
    their constraints rejected, or at a wrong height) registered once more
    against the block solved without them (:func:`reregister_failed`: from
    where their tie points place them, else from their head's solved camera
    and the block's ground), and the bundle solved again with those that
    register. A stage-2 pose that the bundle rejects was found from the
    priors alone (urban-101's S_05: facade edges matched at a wrong height);
    the solved block is a far better start. The new solve is kept unless it
    now rejects or misplaces an image the block held, or rejects the share
    of an image registered again that left it out (its tie points do not
    vouch for it here); then the block and the outcomes go back to what they
    were. ``block``: (state, bundle result, stage 3) after the leave-outs.
    Returns the block and the names of the images registered again
    (``PipelineOptions.reregister_rejected``, off by default).
    """
    by_id = {o.image_id: o for o in outcomes}
    state, first_result, first_stage3 = block
    saved = {i: copy.copy(by_id[i]) for i in left_out}
    workers, init_args = pool_args
    with worker_pool(
        workers, init_args, inputs.cadastre, options.progress, options.dask_scheduler
    ) as pool:
        again_state, names = reregister_failed(
            pool, tasks, outcomes, state, options, ties, only=left_out
        )
    if not names:
        return state, first_result, first_stage3, []
    new_state, result, stage3, verdicts = _solve_again(
        inputs, by_id, again_state, options, timings, ties, names
    )
    rejected, imprecise, misplaced = verdicts
    new = {o.image_id for o in outcomes if o.name in names}
    spoiled = sorted((set(rejected) | set(misplaced)) & set(state.poses))
    # Its second chance stands on its map rows: the tie points that may
    # vouch for an image whose map rows were rejected (ties_confirm) follow
    # its head's weak mode too (urban-101 seed 2: S_05 back 3.5 px off, its
    # map rows 63 % kept, pulling S_01 4.6 px off).
    kept = stage3.constraints_kept
    doubted = sorted(
        i
        for i in new
        if kept.get(i, 1.0) < options.min_constraints_kept
        and not (by_id[i].placed_by_ties and by_id[i].registration.num_inliers == 0)
    )
    if spoiled or doubted:
        why = (
            f"disagreed with {', '.join(by_id[i].name for i in spoiled)}"
            if spoiled
            else "rejected "
            + ", ".join(f"{1 - kept[i]:.0%} of {by_id[i].name}'s" for i in doubted)
            + " map-corner and facade constraints"
        )
        for i in new:
            _restore(by_id[i], saved[i])
            by_id[i].message += (
                "; registered again against the solved block, but the bundle"
                f" with it {why}"
            )
        logger.warning(
            "the bundle with %s registered again %s: they stay left out",
            ", ".join(names),
            why,
        )
        return state, first_result, first_stage3, []
    new_state = _leave_out(new_state, stage3, by_id, rejected, imprecise, misplaced)
    kept = [o.name for o in outcomes if o.image_id in new & set(new_state.poses)]
    return new_state, result, stage3, kept


def _robust_offsets(groups: Sequence[np.ndarray]) -> list[np.ndarray]:
    """Per group of (N_g, D) samples, the (D,) per-component median where it
    differs from zero by more than 3 standard errors, else 0.

    The spread is the pooled standard deviation of all groups (each sample
    about its group's mean, N - G degrees of freedom): the heads of one
    system share their GPS/INS noise, and the spread of a head's three or
    four images alone is too noisy for a test (measured with a MAD per
    group: 25 % false detections with 3 samples, 5 % with 9). A group with
    fewer than 3 samples gets 0. A head's prior errors have a systematic
    part (boresight, lever arm, datum) and a random one; only a part that
    stands out of the random scatter is worth applying to an image that the
    block could not check.
    """
    meds = [np.median(g, axis=0) for g in groups]
    dof = sum(len(g) - 1 for g in groups if len(g))
    if dof < 2:
        return [np.zeros(g.shape[1]) for g in groups]
    ss = sum(np.sum((g - g.mean(axis=0)) ** 2, axis=0) for g in groups if len(g))
    spread = np.sqrt(ss / dof)
    out = []
    for g, m in zip(groups, meds, strict=True):
        stderr = 1.2533 * spread / math.sqrt(len(g))
        ok = len(g) >= 3
        out.append(np.where(ok & (np.abs(m) > 3.0 * stderr), m, 0.0))
    return out


def _block_ground_at(state: BlockState, xy: np.ndarray) -> float:
    """Median over the solved images' ground planes of the height at xy (2,)."""
    planes = np.array(list(state.planes.values()))
    return float(np.median(planes[:, :2] @ xy + planes[:, 2]))


def _footprint_xy(prior: Pose, ground: float) -> np.ndarray:
    """(2,) where the prior's optical axis meets the level z = ground
    (the camera's own xy when the axis does not point down)."""
    axis = prior.rotation[2]  # viewing direction in the world
    c = prior.center
    if axis[2] >= -1e-3:
        return c[:2].copy()
    return c[:2] + (ground - c[2]) / axis[2] * axis[:2]


#: Prior sigmas (centre m, rotation deg) of a start from the tie points: a
#: resection from tens of tracks is good to decimetres and a few hundredths
#: of a degree; these leave room for a weak one.
TIE_START_SIGMAS = (1.0, 0.3)


def _tie_task(
    task: ImageTask,
    camera: Camera,
    start: Pose,
    options: PipelineOptions,
    solved_camera: bool = True,
) -> ImageTask:
    """The task of an image placed by its tie points: the resected pose as a
    tight prior, and its head's solved camera, held (``solved_camera``), or
    the priors' camera of a head with no image in the block, refined as
    stage 2 refines any image's."""
    sigma_m, sigma_deg = TIE_START_SIGMAS
    registration = dataclasses.replace(
        options.registration,
        prior_position_sigma_m=sigma_m,
        prior_rotation_sigma_deg=sigma_deg,
    )
    if solved_camera:
        registration = dataclasses.replace(
            registration,
            refine_focal=False,
            refine_distortion=False,
            prior_focal_sigma=0.0,
        )
    return dataclasses.replace(
        task, start=camera, prior=start, registration=registration
    )


def _placed_by_ties(
    task: ImageTask, pose: Pose, ground: float, failed: RegistrationResult
) -> RegistrationResult:
    """A registration from the tie points alone: the resected pose, the
    head's camera, a level ground at the block's height there, no map
    corner."""
    return RegistrationResult(
        success=True,
        cam_from_world=pose,
        vertical_direction=pose.rotation[:, 2].copy(),
        vertical_source="tie points",
        height_plane=np.array([0.0, 0.0, ground]),
        ground_height=ground,
        num_segments=failed.num_segments,
        message=f"placed by its tie points (the map alone: {failed.message})",
        camera=task.start,
    )


def _head_task(
    task: ImageTask,
    camera: Camera,
    offset: tuple[np.ndarray, np.ndarray],
    options: RegistrationOptions,
) -> ImageTask:
    """The task of a failed image set up against the solved block: it starts
    from its head's solved camera, held (no focal or lens refinement, no
    focal search window), and from its prior corrected by the head's
    systematic offset (rotation vector, centre xy)."""
    rotvec, dxy = offset
    R = rotation_from_axis_angle(rotvec) @ task.prior.rotation
    c = task.prior.center + np.r_[dxy, 0.0]
    registration = dataclasses.replace(
        options, refine_focal=False, refine_distortion=False, prior_focal_sigma=0.0
    )
    return dataclasses.replace(
        task, start=camera, prior=Pose.from_center(R, c), registration=registration
    )


def _head_offsets(
    state: BlockState, heads: dict[int, Sequence[ImageTask]]
) -> dict[int, tuple[np.ndarray, np.ndarray]]:
    """Per head (camera id) its significant systematic prior error: (3,)
    rotation vector in the camera frame (a boresight: solved = R(rotvec) @
    prior, as ``cam_from_world`` rotations) and (2,) centre xy shift (m),
    from its confident images' solved poses against their priors."""
    ids = list(heads)
    rot = [
        np.array(
            [
                axis_angle_from_rotation(
                    state.poses[t.image_id].rotation @ t.prior.rotation.T
                )
                for t in heads[c]
            ]
        )
        for c in ids
    ]
    dxy = [
        np.array(
            [state.poses[t.image_id].center[:2] - t.prior.center[:2] for t in heads[c]]
        )
        for c in ids
    ]
    return dict(
        zip(
            ids,
            zip(_robust_offsets(rot), _robust_offsets(dxy), strict=True),
            strict=True,
        )
    )


def _restore(outcome: ImageOutcome, saved: ImageOutcome) -> None:
    """``outcome`` (the object others refer to) set back to ``saved``."""
    for f in dataclasses.fields(ImageOutcome):
        setattr(outcome, f.name, getattr(saved, f.name))
