"""The vertical vanishing point of an image and the segments through it.

Stage 1b of the pipeline (Habbecke & Kobbelt, section 2.1):

1. Line segments (:mod:`obliq_colmap.lines`), at reduced resolution for big
   images, with lens distortion removed from the endpoints.
2. RANSAC over segment pairs: the intersection of two segments' lines is a
   hypothesis, kept only where the prior (:class:`VPPrior`) allows it, and
   scored by the segments whose line through their midpoint and the
   hypothesis passes near their endpoints (length-weighted MSAC). All
   hypotheses of a batch are evaluated at once.
3. Maximum-likelihood refinement over the inliers: the VP minimising the sum
   of squared endpoint distances to the best line through the VP of each
   segment (the per-segment line is eliminated in closed form), with its
   covariance.
4. Competing VPs: the other strong pencils (street and facade directions)
   are found by RANSAC too, and every segment belongs to the VP it fits best
   (alternating with the ML refinement). In oblique aerial images a street
   seen along the camera's azimuth passes through the nadir point, i.e.
   through the vertical VP: its curbs, markings and parked cars look like
   verticals inside a strip and pulled the VP along it by up to 5 deg. When a
   competitor allowed by the prior is more significant than the vertical (a
   street's many short segments can win the pair-RANSAC), the two swap roles.
   Steps 2-4 run from several starts (``VanishingOptions.start_cones``):
   with an INS prior each in the prior's cone scaled, with the others each
   with its own RANSAC draws; when their VPs disagree, the second pass (5.)
   runs for each and the longest total of vertical segments decides.
5. Second pass (:func:`vertical_segments`): the derivative perpendicular to
   the line from the VP through each pixel, non-maximum suppression and
   hysteresis on it, chains fitted as lines constrained through the VP
   (points within ``end_trim_px`` of a chain's ends, bent by the junction
   with roof or ground, left out of the fit), ends moved out to where the
   contrast halves (the end of the blurred edge). The VP is then refined once
   more on these full-resolution edge points, on the chains within a robust
   noise bound that fit it better than any competing VP. Its covariance is
   the larger of the first pass's and a jackknife over blocks of
   neighbouring chains (``VanishingOptions.second_pass_covariance``; the
   status stays the first pass's unless
   ``status_from_second_pass_covariance``):
   the points of a chain, and the chains of one facade, share their errors,
   so the formal ``2 sigma^2 H^-1`` over independent points is far too small.

Everything is homogeneous (a VP at infinity, ``w = 0``, is legal); internally
pixel coordinates are centred and scaled (``T``) for conditioning. The
vertical direction ``n = +-normalise(K^-1 v)`` is oriented down the world:
``n . d_prior > 0`` with the INS prior's predicted down direction, otherwise
``n_y > 0`` (docs/DESIGN.md, conventions).

Significance: the best hypothesis is judged a contrario: the number of
distinct lines through it that its consistent segments lie on (pieces of one
line, a dashed centre line or a curb behind parked cars, count once:
:mod:`~obliq_colmap.vanishing.collinear`) is compared with the number expected
if the segment orientations were random (Poisson tail, times the number of
hypotheses RANSAC may test), in three length classes (the best counts, the
number of tests tripled). An image without vertical structure (water,
fields, sky, noise) gives a "no_vp" result instead of a confident wrong VP.

Entry function: :func:`detect_vertical_vp` (one grey image in, a
:class:`VanishingResult` out; :func:`estimate_vertical_vp` is steps 2-4 on
given segments, :func:`vertical_segments` step 5 for a given VP).

Data in: the image, (H, W) uint8 (or (H, W, 3) BGR) at full resolution; an
optional :class:`~obliq_colmap.geometry.Camera` (COLMAP pixels, with lens
distortion) and a :class:`VPPrior` (an INS prior holds the predicted down
direction in the camera frame). Data out: the VP as a homogeneous unit
(3,) vector in undistorted COLMAP pixels with its (3, 3) covariance, the
unit vertical direction in the camera frame (with intrinsics), the
first-pass segments with their inlier mask, and the second-pass segments
(:class:`~obliq_colmap.lines.Segments`, undistorted COLMAP pixels, each
through the VP).

Modules, in reading order:

- :mod:`~obliq_colmap.vanishing.options`: :class:`VPPrior`,
  :class:`SecondPassOptions`, :class:`VanishingOptions`,
  :class:`VanishingResult`.
- :mod:`~obliq_colmap.vanishing.pencil`: homogeneous helpers, the best line
  through a VP per group of points, :func:`refine_vp`,
  :func:`vertical_direction`.
- :mod:`~obliq_colmap.vanishing.ransac`: the prior's region, candidate
  segments, RANSAC over segment pairs, the significance test.
- :mod:`~obliq_colmap.vanishing.second_pass`: segments through a known VP
  (:func:`vertical_segments`).
- :mod:`~obliq_colmap.vanishing.refine`: ML refinement against competing VPs,
  and on the second pass's chains.
- :mod:`~obliq_colmap.vanishing.detect`: :func:`estimate_vertical_vp`,
  the starts and :func:`detect_vertical_vp`.

References
----------
M. Habbecke, L. Kobbelt, "Automatic registration of oblique aerial images with
cadastral maps", ECCV workshops 2010, section 2.1.
A. Klaus et al., "MetropoGIS: a semi-automatic city documentation system",
PCV 2002, section 3.1.
A. Almansa, A. Desolneux, S. Vamech, "Vanishing point detection without any a
priori information", PAMI 25, 2003 (the a contrario significance test).
"""

from obliq_colmap.vanishing.detect import detect_vertical_vp, estimate_vertical_vp
from obliq_colmap.vanishing.options import (
    PRIOR_KINDS,
    STATUSES,
    SecondPassOptions,
    VanishingOptions,
    VanishingResult,
    VPPrior,
)
from obliq_colmap.vanishing.pencil import normaliser, refine_vp, vertical_direction
from obliq_colmap.vanishing.second_pass import vertical_segments

__all__ = [
    "PRIOR_KINDS",
    "STATUSES",
    "SecondPassOptions",
    "VPPrior",
    "VanishingOptions",
    "VanishingResult",
    "detect_vertical_vp",
    "estimate_vertical_vp",
    "normaliser",
    "refine_vp",
    "vertical_direction",
    "vertical_segments",
]
