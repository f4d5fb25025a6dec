"""Ground control points: the formats users have, and triangulation in a model.

Entry points:

- :func:`read_control_points` (``read``): OpenSfM/ODM ``gcp_list.txt``
  (``gcp_list``) or OpenSfM's ``ground_control_points.json``
  (``opensfm_json``), recognised by content, into :class:`ControlPoints`
  (``model``): metric projected coordinates (pyproj), observations in
  COLMAP's pixel convention.
- :func:`triangulate_control_points` (``triangulate``): each point from its
  observations in the registered images of any COLMAP model, through the
  model's own cameras; :func:`require_usable`.
- ``residuals``: per point the triangulated-minus-given offset (m) and the
  reprojection of the given position (px), and their summary; shared by
  ``georegister`` and ``evaluate --control_points_path``.
"""

from .model import ControlObservation, ControlPoint, ControlPoints
from .read import read_control_points
from .triangulate import (
    ControlTriangulation,
    require_usable,
    triangulate_control_points,
)

__all__ = [
    "ControlObservation",
    "ControlPoint",
    "ControlPoints",
    "ControlTriangulation",
    "read_control_points",
    "require_usable",
    "triangulate_control_points",
]
