"""Ground control points: the formats users have, and triangulation in a model.

Entry points (the reading and triangulation land with issue 27):

- :class:`ControlPoint`, :class:`ControlObservation`, :class:`ControlPoints`
  (``model``): the points of one file in one metric CRS, with their image
  observations in COLMAP's pixel convention.
"""

from .model import ControlObservation, ControlPoint, ControlPoints

__all__ = ["ControlObservation", "ControlPoint", "ControlPoints"]
