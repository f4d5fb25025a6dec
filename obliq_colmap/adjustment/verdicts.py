"""The verdicts on a solved block: the images stage 3 got wrong.

An image can fit the block badly in three ways the bundle's RMS does not
show; each verdict names the images (ids) and the pipeline leaves them out:

* :func:`rejected_images`: the outlier rounds rejected a large share of its
  constraints (its pose disagrees with the block's);
* :func:`imprecise_images`: its a-posteriori precision is far worse than the
  block's (too few constraints tie it to the others);
* :func:`misplaced_images`: its corners' vertical edges end, feet and tops
  alike, far from where the other images' end (:func:`edge_end_offsets`:
  it sits at a wrong height).

:func:`judge` gives all three as :class:`Verdicts`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np

from obliq_colmap.adjustment.problem import Stage3, vertical_constraints
from obliq_colmap.state import BlockState, ImageOutcome, Inputs

__all__ = [
    "Verdicts",
    "edge_end_offsets",
    "end_offset_ratios",
    "imprecise_images",
    "judge",
    "misplaced_images",
    "rejected_images",
]


class Verdicts(NamedTuple):
    """The images a solved block is judged to be wrong about, by id (sorted)."""

    #: The bundle disagrees with them: it rejected too many of their
    #: constraints (:func:`rejected_images`).
    rejected: list[int]
    #: It determines their pose too poorly (:func:`imprecise_images`).
    imprecise: list[int]
    #: It left them at a wrong height: their edges' ends
    #: (:func:`misplaced_images`).
    misplaced: list[int]


def judge(
    stage3: Stage3,
    min_constraints_kept: float,
    max_precision_ratio: float,
    max_end_offset_ratio: float,
) -> Verdicts:
    """The three verdicts on a solved block (:class:`Verdicts`); each limit
    as its function takes it (0: that verdict flags no image)."""
    return Verdicts(
        rejected_images(stage3, min_constraints_kept),
        imprecise_images(stage3, max_precision_ratio),
        misplaced_images(stage3, max_end_offset_ratio),
    )


def rejected_images(stage3: Stage3, min_kept: float) -> list[int]:
    """The images whose constraints the bundle rejected in large part.

    The outlier rounds reject some of every image's constraints (map
    corners and facade observations together: at most 26 % in 18 `paper`
    and `hard` runs for every image that ends < 2 px off). An image the
    bundle leaves metres off along its verticals, where its own corners and
    facade edges no longer fit the block, loses more (in those runs 6 of the
    7 images that end > 5 px off, and one at 4.6 px: 31-49 %; the seventh
    kept 81 %), and its RMS does not show it (the rows kept fit). A share
    below ``min_kept`` flags it, unless its tie points say otherwise
    (:func:`ties_confirm`).
    """
    confirmed = ties_confirm(stage3)
    return sorted(
        i
        for i, k in stage3.constraints_kept.items()
        if math.isfinite(k) and k < min_kept and i not in confirmed
    )


#: Tie observations an image needs for its tie points to vouch for its pose
#: (as many as place an image by its tie points: pipeline.resection).
MIN_TIE_OBSERVATIONS = 30


def ties_confirm(stage3: Stage3) -> set[int]:
    """The images whose tie points fit the block as well as most images'.

    An image's map rows can be poor where its pose is right (urban-101's
    facades in shadow: E_05, S_03, S_05 lost 41-47 % of them and were 0.9-1.1
    px off, their 164-378 tie observations at a median error of 0.22-0.30 px
    against the block's 0.26). Its tie points are evidence the map rows are
    not, where they tie it to another head (its own head's images share its
    weak mode, and tie points among them follow it: urban-101 seed 2, S_05
    13.7 px off with 104 observations at a typical error, 24 of them across
    heads): at least :data:`MIN_TIE_OBSERVATIONS` observations of points
    another head sees (:attr:`Stage3.tie_fit`), and a median error within the
    90th percentile of the images' medians, confirm it. (`paper` s3: N_11, 5
    px off, had 44 at 1.7x the block's median; W_11, 12 px off, none.)
    """
    fit = stage3.tie_fit
    if len(fit) < 4:
        return set()
    limit = float(np.quantile([m for _, m in fit.values()], 0.9))
    return {i for i, (n, m) in fit.items() if n >= MIN_TIE_OBSERVATIONS and m <= limit}


def imprecise_images(
    stage3: Stage3, max_ratio: float, min_images: int = 4
) -> list[int]:
    """The images whose pose the bundle determines far worse than the block's.

    Each image's a-posteriori precision (:attr:`Stage3.bundle_precision`,
    px) against the median over the block: an image held along its
    verticals by little more than two-view facade tracks (whose offset and
    height absorb a shift of either camera) has a predicted sd several times
    the block's, and there the bundle can leave it metres off with every
    constraint kept and its RMS unremarkable. A ratio above ``max_ratio``
    flags it (0: none); the median needs ``min_images`` finite values. The
    precision is internal: it does not see wrong matches
    (:func:`rejected_images` does).
    """
    sd = {i: v for i, v in stage3.bundle_precision.items() if math.isfinite(v)}
    if max_ratio <= 0 or len(sd) < min_images:
        return []
    limit = max_ratio * float(np.median(list(sd.values())))
    return sorted(i for i, v in sd.items() if v > limit)


def edge_end_offsets(
    inputs: Inputs,
    outcomes: dict[int, ImageOutcome],
    state: BlockState,
    image_ids: Sequence[int],
    min_corners: int = 5,
    measured_directions: bool = False,
) -> dict[int, np.ndarray]:
    """Per image: how far its corners' vertical edges end, along its
    verticals, from where the other images' edges end: (2,) px, + up, the
    feet and the tops.

    Each inlier segment of stage 2 ends near the foot and the top of its
    corner's edge. Cast through the image's solved camera onto the corner's
    vertical, both ends get heights; per corner and end, the other images'
    median height is the block's. Per end, the image's offset is the median
    over its corners of (own height - block's height) in pixels along its
    vertical. Either end alone can be off for reasons of its own (feet cut
    by cars and trees, tops by roof rims seen from another side), but an
    image whose camera the bundle left off along its verticals (its facade
    edges matched a floor off, say) moves both together, which its
    corner-to-line and facade rows cannot show. Absent for an image sharing
    fewer than ``min_corners`` corners with the others.
    """
    v = vertical_constraints(inputs, outcomes, state, image_ids, measured_directions)
    if not len(v["xy"]):
        return {}
    # Two rows per segment (its ends); order each pair foot, top.
    h = np.sort(v["height"].reshape(-1, 2), axis=1)
    img, corner, xy = v["image"][::2], v["corner"][::2], v["xy"][::2]
    corners, col = np.unique(corner, return_inverse=True)
    table = np.full((2, len(image_ids), len(corners)), np.nan)  # end x image x corner
    table[:, img, col] = h.T
    out = {}
    for k, i in enumerate(image_ids):
        sel = img == k
        if sel.sum() < min_corners:
            continue
        others = np.delete(table[:, :, col[sel]], k, axis=1)  # (2, I-1, n)
        # Both ends of a segment are always there together: a corner another
        # image saw has both.
        seen = np.isfinite(others[0]).any(axis=0)
        if seen.sum() < min_corners:
            continue
        block = np.nanmedian(others[:, :, seen], axis=1)  # (2, s)
        # Pixels per metre along the vertical at each corner, solved camera.
        cam, pose = state.cameras[i], state.poses[i]
        X = np.column_stack([xy[sel][seen], h[sel][seen].mean(axis=1)])
        up = cam.img_from_cam(pose.transform(X + [0.0, 0.0, 0.5]))
        down = cam.img_from_cam(pose.transform(X - [0.0, 0.0, 0.5]))
        d = (h[sel][seen].T - block) * np.linalg.norm(up - down, axis=1)  # (2, s)
        out[i] = np.median(d, axis=1)
    return out


def end_offset_ratios(
    stage3: Stage3, min_images: int = 4, floor_px: float = 0.2
) -> dict[int, float]:
    """Per image id: how many of the block's spreads both ends of its
    vertical edges sit off, in the same direction (0 where they disagree).

    Per end (feet, tops), each image's :attr:`Stage3.end_offset_px` from the
    block's median over the images, in the block's robust spread (1.4826
    MAD, at least ``floor_px``: the ends are found to about a pixel, and
    below that a ratio would count sub-pixel offsets); the smaller of the
    two. Empty with fewer than ``min_images`` images with offsets.
    """
    ids = [i for i, v in stage3.end_offset_px.items() if np.all(np.isfinite(v))]
    if len(ids) < min_images:
        return {}
    off = np.array([stage3.end_offset_px[i] for i in ids])  # (I, 2)
    centre = np.median(off, axis=0)
    spread = np.maximum(1.4826 * np.median(np.abs(off - centre), axis=0), floor_px)
    z = (off - centre) / spread
    both = np.where(z[:, 0] * z[:, 1] > 0, np.abs(z).min(axis=1), 0.0)
    return dict(zip(ids, both.tolist(), strict=True))


def misplaced_images(stage3: Stage3, max_ratio: float) -> list[int]:
    """The images whose vertical edges end, feet and tops alike, far from
    where the block's do: :func:`end_offset_ratios` above ``max_ratio`` (0:
    none)."""
    if max_ratio <= 0:
        return []
    return sorted(i for i, r in end_offset_ratios(stage3).items() if r > max_ratio)
