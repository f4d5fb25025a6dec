"""The leave-outs: the images stage 3's verdicts name
(:func:`block_verdicts`) leave the block as failures that say why
(:func:`leave_out_rejected`); the written images the bundle determines
worse than the registration criterion (:func:`warn_imprecise`) and those
whose own vanishing point contradicts them (:func:`warn_vp_disagreement`) are
named; without the block (``--stop_after initial``), so are the images
registered without a vertical vanishing point of their own
(:func:`warn_unconfirmed_vertical`).
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

import numpy as np

from obliq_colmap.adjustment import Stage3, Verdicts, judge
from obliq_colmap.pipeline.options import PipelineOptions
from obliq_colmap.state import BlockState, ImageOutcome

__all__ = [
    "UNCONFIRMED_VERTICAL_NOTE",
    "block_verdicts",
    "leave_out_rejected",
    "unsupported_placements",
    "warn_imprecise",
    "warn_unconfirmed_vertical",
    "warn_vp_disagreement",
]

logger = logging.getLogger(__name__)

#: How :func:`warn_unconfirmed_vertical`'s note begins (only a run that stops
#: after stage 2 writes it; the split benchmarks take it out again).
UNCONFIRMED_VERTICAL_NOTE = "written with a warning: its vertical vanishing point was"


def block_verdicts(stage3: Stage3, options: PipelineOptions) -> Verdicts:
    """The images the bundle disagrees with (too many of their constraints
    rejected), those it determines too poorly (precision) and those it left
    at a wrong height (their edges' ends), by id: stage 3's verdicts
    (:func:`~obliq_colmap.adjustment.judge`) with the run's limits."""
    return judge(
        stage3,
        options.min_constraints_kept,
        options.max_precision_ratio,
        options.max_end_offset_ratio,
    )


def tie_support(stage3: Stage3) -> dict[int, int]:
    """Per image id of the last bundle: its tie observations of points that
    at least two other images observe too (what a tie resection stands on:
    a point seen by one other image only is free along that image's ray)."""
    P = stage3.bundle_problem
    if P is None or len(P.tie_point) == 0:
        return {}
    length = np.bincount(P.tie_point)[P.tie_point]
    n = np.bincount(P.tie_image[length >= 3], minlength=len(P.image_ids))
    return {i: int(n[k]) for k, i in enumerate(P.image_ids)}


def unsupported_placements(
    state: BlockState,
    stage3: Stage3 | None,
    outcomes: dict[int, ImageOutcome],
    min_observations: int,
) -> list[int]:
    """The written images placed by their tie points alone (no map corner
    of their own) that the last bundle no longer holds so: fewer than
    ``min_observations`` (the resection's own minimum) of their tie
    observations on points two other images see (:func:`tie_support`; the
    rounds dropped the rest as outliers, or they were never there). What is
    left holds the pose along epipolar lines only (houses-102, stage-2 seed
    1: E_01 written 165 px off on 1 such observation of 47)."""
    if stage3 is None:
        return []
    support = tie_support(stage3)
    return sorted(
        i
        for i in state.poses
        if outcomes[i].placed_by_ties
        and outcomes[i].registration is not None
        and outcomes[i].registration.num_inliers == 0
        and support.get(i, 0) < min_observations
    )


def leave_out_rejected(
    state: BlockState,
    stage3: Stage3 | None,
    outcomes: dict[int, ImageOutcome],
    rejected: Sequence[int],
    imprecise: Sequence[int] = (),
    misplaced: Sequence[int] = (),
    unsupported: Sequence[int] = (),
) -> BlockState:
    """The block without the images the (last) bundle disagrees with
    (``rejected``), determines too poorly (``imprecise``), left at a wrong
    height (``misplaced``) or no longer holds where their tie points placed
    them (``unsupported``, :func:`unsupported_placements`); their outcomes
    become failures that say why."""
    out = sorted(
        {
            i
            for i in [*rejected, *imprecise, *misplaced, *unsupported]
            if i in state.poses
        }
    )
    if not out or stage3 is None:
        return state
    support = tie_support(stage3) if unsupported else {}
    sd = [v for v in stage3.bundle_precision.values() if math.isfinite(v)]
    median_sd = float(np.median(sd)) if sd else math.nan
    for i in out:
        reasons = []
        if i in rejected:
            reasons.append(
                f"the bundle rejected {1 - stage3.constraints_kept[i]:.0%} of its"
                " map-corner and facade constraints (its pose disagrees with the"
                " block's)"
            )
        if i in imprecise:
            reasons.append(
                "the bundle determines its pose poorly (predicted sd"
                f" {stage3.bundle_precision[i]:.2f} px against the block's median"
                f" {median_sd:.2f} px: too few constraints tie it to the"
                " others)"
            )
        if i in misplaced:
            reasons.append(
                "its corners' vertical edges end {:+.1f} px (feet) and {:+.1f}"
                " px (tops) along its verticals from where the other images'"
                " end (it sits at a wrong height, e.g. facade edges matched a"
                " floor off)".format(*stage3.end_offset_px[i])
            )
        if i in unsupported:
            reasons.append(
                f"placed by its tie points, but only {support.get(i, 0)} of its tie"
                " observations in the last bundle are of points two other"
                " images see (too few to hold the placement)"
            )
        o = outcomes[i]
        o.status = "failed"
        o.message = "left out: " + "; ".join(reasons)
        logger.warning("%s: %s", o.name, o.message)
    return state.without(out)


def _add_note(outcome: ImageOutcome, note: str) -> None:
    """Append ``note`` to the image's message (its status stays)."""
    outcome.message = f"{outcome.message}; {note}" if outcome.message else note


def warn_imprecise(
    state: BlockState,
    stage3: Stage3 | None,
    outcomes: dict[int, ImageOutcome],
    max_sd_px: float,
) -> list[int]:
    """Name the written images whose predicted deviation (the last bundle's
    sd of their projections, :attr:`Stage3.bundle_precision`) exceeds
    ``max_sd_px``: one warning for the block, the reason in each image's
    message. They stay in the block (the sd is a statement about the
    block's information, not evidence that this pose is wrong). Returns
    their ids."""
    if stage3 is None:
        return []
    precision = stage3.bundle_precision
    # A NaN sd: the bundle's covariance of that pose is not positive (the
    # image is held by too little, e.g. placed by its tie points alone);
    # that is no precision at all (houses-102 E_00, 2026-12-05: written
    # 6726 px off with NaN and no warning). An image without an entry (no
    # covariance computed) is not judged.
    undetermined = sorted(
        i for i in state.poses if i in precision and not math.isfinite(precision[i])
    )
    weak = sorted(i for i in state.poses if precision.get(i, math.nan) > max_sd_px)
    for i in undetermined:
        _add_note(
            outcomes[i],
            "written with a warning: the bundle cannot state its precision (its"
            " pose's covariance is not positive), so it may be more than 2 px off",
        )
    if undetermined:
        logger.warning(
            "%d of %d written images have no precision from the bundle (they may"
            " be more than 2 px off): %s",
            len(undetermined),
            len(state.poses),
            ", ".join(outcomes[i].name for i in undetermined),
        )
    for i in weak:
        _add_note(
            outcomes[i],
            f"written with a warning: the bundle predicts its projections to"
            f" {precision[i]:.2f} px (sd; above {max_sd_px:g} px),"
            " so it may be more than 2 px off",
        )
    if weak:
        sd = [precision[i] for i in weak]
        # the block's own level: many names in a block near the threshold
        # say the block as a whole is that precise, not that they are worse
        block = [v for i, v in precision.items() if i in state.poses]
        logger.warning(
            "%d of %d written images are determined worse than %g px (predicted"
            " sd %.2f-%.2f px, the block's median %.2f px; they may be more than"
            " 2 px off): %s",
            len(weak),
            len(state.poses),
            max_sd_px,
            min(sd),
            max(sd),
            float(np.nanmedian(block)),
            ", ".join(outcomes[i].name for i in weak),
        )
    return sorted(weak + undetermined)


def warn_vp_disagreement(
    state: BlockState, stage3: Stage3 | None, outcomes: dict[int, ImageOutcome]
) -> list[int]:
    """Name the written images whose vertical VP the bundle's rounds
    rejected against the block (:attr:`Stage3.vp_rejected`): the image's
    own vertical and its solved pose disagree beyond the VP's covariance and
    the block's, so one of the two is wrong, and the rows that hold the pose
    may be a consistent wrong set (a registration on a few corners more than
    chance: our generator's dense class, an image written 5 px and 0.69 deg
    off whose VP the block rejected at 0.63 deg, with a predicted sd of 0.7
    px). One warning for the block, the reason in each image's message; they
    stay in the block (a wrong VP rejects the same way). Returns their ids."""
    if stage3 is None:
        return []
    named = sorted(i for i in state.poses if i in stage3.vp_rejected)
    for i in named:
        _add_note(
            outcomes[i],
            "written with a warning: its vertical vanishing point and its solved"
            f" pose disagree by {stage3.vp_rejected[i]:.2f} deg (rejected against"
            " the block), so one of them is wrong and it may be more than 2 px off",
        )
    if named:
        logger.warning(
            "%d written images disagree with their own vertical vanishing point"
            " (one of the two is wrong; they may be more than 2 px off): %s",
            len(named),
            ", ".join(
                f"{outcomes[i].name} ({stage3.vp_rejected[i]:.2f} deg)" for i in named
            ),
        )
    return named


def warn_unconfirmed_vertical(outcomes: Sequence[ImageOutcome]) -> list[str]:
    """Name the registered images whose vertical stage 1 did not confirm
    (its VP "low_confidence" or "no_vp"), for a run that stops before the
    block: such an image's tilt comes from the prior and stage 2's own
    search, and nothing else checks it (houses-102, ``--stop_after
    initial``: the four images written 13-22 px off across the verticals
    were all such images, with 13-23 inlier corners against a chance level
    of 8-9; the full run tests them against the block). One warning for the
    run, the reason in each image's message; they stay written. Returns
    their names."""
    named = [
        o
        for o in outcomes
        if o.registered and o.vp_status in ("low_confidence", "no_vp")
    ]
    for o in named:
        status = "not found" if o.vp_status == "no_vp" else "of low confidence"
        _add_note(
            o,
            f"{UNCONFIRMED_VERTICAL_NOTE} {status},"
            " so its tilt rests on the prior and the map corners alone and it may"
            " be more than 2 px off (the full run checks it against the block)",
        )
    if named:
        logger.warning(
            "%d of %d registered images have no confirmed vertical vanishing point"
            " (they may be more than 2 px off; the full run checks them against"
            " the block): %s",
            len(named),
            sum(o.registered for o in outcomes),
            ", ".join(o.name for o in named),
        )
    return [o.name for o in named]
