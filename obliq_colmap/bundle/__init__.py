"""Stage 3: the global cadastral-line bundle adjustment (paper section 2.3, eq. 3).

Entry: :func:`solve_bundle` (:class:`BundleProblem`, :class:`BundleOptions`)
-> :class:`BundleResult`. The caller (``obliq_colmap.adjustment``) builds the
problem from the registered images, the map and the facade tracks.

Unknowns: per image the 6 extrinsics (rotation, camera centre), per camera
(COLMAP camera_id, shared by all images of one head) the refined intrinsic
parameters, and scalar heights: one per facade-edge constraint j (``h_j``)
and, by default, one per map corner (``h_i``, shared by the corner's
observations in all images).

Residuals (all in pixels, with analytic Jacobians for every supported COLMAP
camera model):

* vertical: signed distance of the projected corner ``(x_i, y_i, h_i)`` to
  the detected vertical image line; with
  ``BundleOptions.vertical_direction_sigma_px`` the two rows of one segment
  (its two ends, :func:`vertical_row_pairs`) enter as their sum and
  difference, each with its own sd (the map's noise moves both ends alike);
* horizontal: ``dist_z``, the distance of the projected facade point
  ``(x_j, y_j, h_j)`` to the detected horizontal line, measured along the
  projected vertical;
* tie points (optional, ``BundleProblem.tie_*``): features matched across
  the images, each a free 3D point, two reprojection rows per observation;
  the points are eliminated by their 3x3 blocks (:mod:`.ties`); a tie
  point's coordinates may be observed too (``tie_prior_xyz``: control
  points, rows on its own block).
* facade lines (``BundleOptions.facade_lines``, off by default): each level
  facade track a horizontal 3D line (height, offset, direction) observed at
  both ends of every segment, eliminated by its 3x3 block
  (:mod:`.facade_lines`), instead of the horizontal rows and heights above.

Observed camera parameters (``priors``; each optional): INS attitude, GNSS
centres, the principal points, and each image's vertical vanishing point
(stage 1's VP with its covariance, ``BundleOptions.vp_observations``: 2 rows,
the angle between the world's vertical as the camera sees it and the VP's
direction through the camera's current intrinsics, robust).

Data in (:class:`BundleProblem`, local map frame, metres, x east, y north):
cameras (camera_id -> Camera) and initial ``cam_from_world`` poses (image_id
-> Pose); (C, 2) map corners with (C,) initial heights; M vertical
constraints (image index, corner index, (M, 3) homogeneous image line in
pixels); J facade heights and H horizontal constraints (image index, height
index, (H, 2) anchor xy, (H, 3) image line); optional INS rotations and GNSS
centres per image.

Data out (:class:`BundleResult`): refined copies of the cameras and poses,
(J,) facade and (C,) corner heights (m), the final (M,) and (H,) residuals
(px) in the problem's order, a :class:`BundleSummary` (costs, RMSEs,
iterations, linked components), each image's predicted precision (px), the
variance factor and, with GNSS priors, the priors' horizontal offset (m).

Modules, in reading order:

- ``problem``: :class:`BundleOptions`, :class:`BundleProblem`,
  :class:`BundleSummary`, :class:`BundleResult`, :func:`image_components`.
- ``projection``: every supported camera model through one 8-parameter
  form; projection with analytic Jacobians.
- ``residuals``: the vertical and horizontal residual rows and their
  Jacobians (pose, intrinsics, height).
- ``coupling``: the layout of the sparse height-camera coupling E and its
  products.
- ``setup``: the static layout of one solve (residual order, parameter
  columns, components, gauge rows), the state of the unknowns and the
  evaluation of residuals and Jacobians.
- ``schur``: normal equations, the Schur complement on the heights and the
  damped step.
- ``loss``: the robust losses.
- ``blocks``: unknowns eliminated by their 3x3 blocks (layout and algebra).
- ``ties``: the tie points' reprojection rows (:mod:`.blocks`).
- ``facade_lines``: the facade tracks as 3D horizontal lines (:mod:`.blocks`).
- ``priors``: the observed poses (INS attitude, GNSS centres), principal
  points and vertical vanishing points.
- ``covariance``: the camera block's a-posteriori covariance and each
  image's precision.
- ``solver``: :func:`solve_bundle`, the robust loss and the
  Levenberg-Marquardt loop.

Synthetic problems with exact ground truth (tests, benchmark) are made by
:mod:`obliq_colmap.synthetic.bundle_problem`.
"""

from .problem import (
    BundleOptions,
    BundleProblem,
    BundleResult,
    BundleSummary,
    image_components,
    vertical_row_pairs,
)
from .solver import solve_bundle

__all__ = [
    "BundleOptions",
    "BundleProblem",
    "BundleResult",
    "BundleSummary",
    "image_components",
    "solve_bundle",
    "vertical_row_pairs",
]
