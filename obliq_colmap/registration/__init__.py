"""Initial registration of one oblique image to the cadastral map (stage 2).

Habbecke & Kobbelt, section 2.2: with the vertical vanishing point known, the
pose has four unknowns, ``T(alpha, c) = R_vanish R_z(alpha) (I | -c)`` (eq. 1),
found from correspondences between map corners and vertical image segments.
Here the camera height is held at the prior (docs/DESIGN.md, "height gauge"): a
vertical-line constraint cannot see it, so three unknowns (alpha, c_x, c_y)
remain and a sample of three pairs determines them in closed form
(:mod:`~obliq_colmap.registration.ransac_core`).

Entry: :func:`register_image` (one image; a pure function, safe in a process
pool, deterministic for ``options.seed``).

In: the image's vertical segments ``segments_px`` (N, 2, 2) COLMAP pixels
(distorted as detected, or undistorted pixels of the pinhole part); the
vertical direction (3,) in the camera frame, pointing down the world (from the
vanishing stage, or None); the rough ``Camera``; the prior ``cam_from_world``
``Pose`` in the cadastre's LOCAL frame (metres; its height in an unknown
vertical datum); the ``Cadastre`` (corners and edges, local metres).

Out: a :class:`RegistrationResult`: the pose (local frame, camera height held
at the prior's), the refined camera, the inlier pairs (K, 2) (cadastre corner,
input segment), their segments (K, 2, 2) undistorted pixels, the height plane
``z = a x + b y + c`` (3,) of the ground and the ground height (m, the priors'
datum). A failure is a result with ``success=False`` and a message, never
raised.

Steps of :func:`register_image`:

1. Frame. ``R_vanish`` is the prior rotation, minimally rotated so that its
   vertical agrees with the detected one (or the prior's own vertical when the
   VP detection failed); ``alpha`` is the heading correction from the prior.
   Segment endpoints are undistorted; each segment's line is taken through
   the VP and its endpoint nearer the nadir is its bottom.
2. Ground height and coarse pose (Hough). The priors' heights are in an
   unknown datum, so the ground height is searched with the pose: the
   (corner, segment) pairs within the search radius across the corner's
   projected vertical at the prior pose vote over a coarse grid of (alpha,
   c_x, c_y, height). For each alpha a pair's constraint is a straight line
   in the (c_x, c_y) plane, rasterised into the accumulator at the height of
   the segment's bottom on the corner's vertical at that pose. The best pose
   at each of the ``num_candidates_verified`` strongest heights is a start;
   where fewer heights compete (a given ground height), the next strongest
   poses fill the starts up to that number.
3. Fine pose (Hough). From each start, the pairs near its ground height vote
   over a fine grid of (alpha, c_x, c_y) a few coarse cells wide. The peak
   leaves a few pixels of error, so RANSAC runs in a small radius.
4. RANSAC. Candidates: pairs within ``ransac_radius_px`` across and
   ``candidate_height_tolerance_m`` of the ground. Samples of three pairs
   (distinct corners and segments), hypotheses from the closed-form solver in
   batches; for each, the linear height function through the samples'
   bottom heights (paper, Fig. 3b) and the elliptical Mahalanobis test of
   every candidate: across the segment ``inlier_threshold_px``, along it
   ``along_segment_stretch`` times more, measured from the segment's bottom
   to the corner projected at the height function. Score: the number of
   distinct inlier corners. Adaptive number of trials for ``confidence``.
   Each start gets a short RANSAC (``verify_trials``); the one with the most
   inlier corners is resumed to the full RANSAC.
5. Refinement. Levenberg-Marquardt (scipy, robust Huber loss) over (alpha,
   c_x, c_y) of the height-free geometric residual: the distances of both
   endpoints of each inlier segment to the image of its corner's vertical
   (eq. 2 without the heights; this avoids the collapse towards the VP of the
   plain point-to-line distance). Whole buildings whose median residual stays
   above the threshold are dropped (a building shifted in the map must not
   pull the pose), then all pairs are re-scored with the refined pose and
   height plane, and refined once more.

Then the chance test (:func:`chance_test`): a weak result must beat the same
search with the segments mirrored. For the images of one lens the pipeline
finds one focal length (:func:`focal_profile`, :func:`consensus_peak`) and
refines each image with it (:func:`refine_with_camera`).

Modules, in reading order (imports go one way, each from those above it):

- ``options``: :class:`RegistrationOptions`, :class:`RegistrationResult`,
  the inlier threshold at an image's scale.
- ``ransac_core``: the closed-form minimal solver and generic RANSAC helpers
  (trial count, sampling).
- ``view``: the VP-aligned frame of one image, height planes.
- ``segments``: usable segments, pairs near a pose, Mahalanobis distances.
- ``raster``: rasterisation of the Hough vote's lines of cells.
- ``hough``: the Hough votes (steps 2-3) and their peaks.
- ``ransac``: candidates, scoring, the RANSAC loop (step 4).
- ``refine``: inlier assignment, Levenberg-Marquardt, lens, refine rounds
  (step 5).
- ``tries``: steps 3-4 from one coarse peak.
- ``search``: steps 1-5 of one image.
- ``register``: :func:`register_image`, the chance test,
  :func:`block_ground_height`.
- ``reassociate``: :func:`refine_with_camera` (a result with another camera).
- ``head_focal``: :func:`focal_profile`, :func:`consensus_peak`.
- ``overlay``: :func:`draw_registration_overlay`.

References
----------
M. Habbecke, L. Kobbelt, "Automatic registration of oblique aerial images with
cadastral maps", ECCV workshops 2010, section 2.2.
R. O. Duda, P. E. Hart, "Use of the Hough transformation to detect lines and
curves in pictures", CACM 15(1), 1972.
"""

from obliq_colmap.registration.head_focal import consensus_peak, focal_profile
from obliq_colmap.registration.options import (
    RegistrationOptions,
    RegistrationResult,
    inlier_threshold_px,
)
from obliq_colmap.registration.overlay import (
    OVERLAY_COLORS,
    draw_registration_overlay,
)
from obliq_colmap.registration.reassociate import refine_with_camera
from obliq_colmap.registration.refine import radial_index
from obliq_colmap.registration.register import (
    block_ground_height,
    chance_counts,
    chance_test,
    register_image,
)

__all__ = [
    "OVERLAY_COLORS",
    "RegistrationOptions",
    "RegistrationResult",
    "block_ground_height",
    "chance_counts",
    "chance_test",
    "consensus_peak",
    "draw_registration_overlay",
    "focal_profile",
    "inlier_threshold_px",
    "radial_index",
    "refine_with_camera",
    "register_image",
]
