"""Images that SfM left out, placed from vanishing points (MetropoGIS 3.2.2).

An image in ``--image_path`` that the SfM model does not hold gets its pose
from a registered neighbour:

1. **Its VP triplet.** Stage 1 (:func:`~obliq_colmap.vanishing.detect_vertical_vp`,
   a terrestrial prior) gives the vertical direction ``d`` in the camera
   frame and the image's segments. The horizontal VPs are found by RANSAC
   over the other segments (:func:`horizontal_vps`): with ``d`` known, ONE
   segment is a hypothesis (the horizontal direction in the segment's
   interpretation plane, ``h = n x d``), and the segments whose lines pass
   near the VP ``K h`` support it. ``(h, d x h, d)`` is the image's
   orthogonal triplet; more facade directions give more triplets.
2. **The rotation** (:func:`rotation_candidates`): a horizontal direction of
   the new image and one of the neighbour's (rotated into the model frame
   by the neighbour's pose), with the model's down for ``d``, give
   ``cam_from_world``; each pairing and sign is a candidate (a facade seen
   from both sides, or its perpendicular, look alike). Candidates farther
   than ``max_rotation_from_reference_deg`` from the reference (the image's
   prior rotation where given, else the neighbour's) are dropped; the
   position step decides among the rest.
3. **The position** (:func:`centre_from_rotation`): SIFT (pycolmap) against
   the neighbours, the matches verified by pycolmap's two-view geometry, the
   neighbour's keypoints looked up among its points2D with a 3D point of the
   model. With the rotation known, one 2D-3D correspondence puts the centre
   on a line (the ray through the 3D point, 2 equations), so TWO are the
   minimal sample (4 equations for 3 unknowns; a linear least-squares
   solve). MetropoGIS gets by with one POI pair because its pair has no
   scale (a base direction, 2 DOF, plus a 1-D search along the ray for
   support); against a model's metric points the scale is fixed and one
   point leaves the centre free along its ray. RANSAC over pairs, every
   hypothesis at once; the winner refined on its inliers.

It needs a building with horizontal lines that the new image and a
neighbour both see (a facade or its perpendicular), and at least a few
matches whose neighbour keypoints are SfM track observations; it refuses
(``status`` not "placed", with a message) otherwise.

References
----------
A. Klaus, J. Bauer, K. Karner, K. Schindler, "MetropoGIS: a semi-automatic
city documentation system", PCV 2002, section 3.2.2.

Modules: :mod:`.options` (options, results), :mod:`.vps` (steps 1-2),
:mod:`.position` (step 3), :mod:`.matching` (the correspondences),
:mod:`.place` (one image end to end; all missing images of a model).
"""

from .matching import (
    Correspondences,
    Features,
    RegisteredImages,
    correspondences_2d3d,
    missing_images,
    neighbour_candidates,
    neighbour_order,
    pool_directions,
    read_gray,
    sift,
    track_correspondences,
    verified_matches,
)
from .options import (
    PLACEMENT_STATUSES,
    HorizontalVPs,
    ImageVPs,
    PlacedImage,
    RelativeVPOptions,
)
from .place import (
    MissingImage,
    add_missing_images,
    place_image,
    place_prepared,
    prepare_image,
    write_placed,
)
from .position import centre_from_rotation, place_with_rotations
from .vps import horizontal_vps, image_vps, rotation_candidates

__all__ = [
    "PLACEMENT_STATUSES",
    "Correspondences",
    "Features",
    "HorizontalVPs",
    "ImageVPs",
    "MissingImage",
    "PlacedImage",
    "RegisteredImages",
    "RelativeVPOptions",
    "add_missing_images",
    "centre_from_rotation",
    "correspondences_2d3d",
    "horizontal_vps",
    "image_vps",
    "missing_images",
    "neighbour_candidates",
    "neighbour_order",
    "place_image",
    "place_prepared",
    "place_with_rotations",
    "pool_directions",
    "prepare_image",
    "read_gray",
    "rotation_candidates",
    "sift",
    "track_correspondences",
    "verified_matches",
    "write_placed",
]
