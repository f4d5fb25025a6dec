"""Second workflow (MetropoGIS): bring an existing COLMAP SfM model onto the map.

Entry: :func:`georegister` (``run``; ``obliq-colmap georegister``), the
model in, a :class:`GeoregisterResult` out (the model in a local frame of
the map, its ``Georef`` and the report), written by the command.

Modules, in the order a run uses them:

- ``options``: :class:`GeoregisterOptions`, :class:`VerticalOptions`.
- ``common``: reading the SfM model, turning it upright, the result.
- ``vertical``: the model's down direction from its images' vertical VPs
  (stage 1; a robust mean on the sphere; ``--camera_kind auto`` keeps the
  prior whose images agree).
- ``similarity``: with control points, the 4-DOF similarity (closed form
  from two, robust weighted least squares from more; 7-DOF without a
  vertical).
- ``map_rows``: the map's corner lines as rows of the block adjustment.
- ``facade_rows``: the map's facade edges, matched across the images into
  tracks of one height, as rows of the block adjustment.
- ``block``: the bundle block adjustment (the SfM tracks, control point
  priors by their sigmas, each image's VP as an observation of its
  vertical, the map rows; principal point and distortion refined) in the
  project's bundle (``block_bundle``) or, as its check, in pycolmap's Ceres
  adjuster (``block_ceres``).
- ``uncertainty``: report.json's ``uncertainty`` section, each camera's sds
  from the adjustment's covariance.
- ``relative_vp``: with ``--add_missing_images 1``, images that SfM left
  out: their rotation from VPs against a registered neighbour (MetropoGIS
  3.2.2), their centre from two or more matches to the model's points.
- ``automatic`` and ``run_automatic``: without control points, stage 2 on
  every image from the priors' positions, then one similarity fitted to all
  their corner-to-ray pairs (oblique cameras); for level cameras (a street;
  ``automatic_method``) ``sight``, ``block_lines`` and ``lines_placement``:
  all images' vertical segments against the map's corners in sight at once,
  the heading prior from the priors' rotations too.
- ``run``: :func:`georegister` (the control-point mode, and the dispatch).
"""

from .common import GeoregisterResult
from .options import GeoregisterOptions, VerticalOptions
from .run import georegister

__all__ = ["GeoregisterOptions", "GeoregisterResult", "VerticalOptions", "georegister"]
