"""The inspection report of a registration and the cameras' uncertainty.

* :mod:`~obliq_colmap.report.uncertainty`: per-camera position and rotation
  sds and the predicted deviation in pixels from the bundle's covariance
  (written by ``register`` into report.json's ``uncertainty`` section).
* :mod:`~obliq_colmap.report.overlays`: the map projected onto each image
  with the priors' pose (before) and the result's (after), as JPEGs.
* :mod:`~obliq_colmap.report.svg`: histograms and the plan view (cameras,
  error ellipses over the map) as inline SVG, drawn by hand: no plotting
  dependency, and the page stays crisp and self-contained.
* :mod:`~obliq_colmap.report.page`: the HTML page.
* :mod:`~obliq_colmap.report.build`: :func:`build_report`, the
  ``obliq-colmap report`` subcommand's one call.
"""

from obliq_colmap.report.uncertainty import (
    TRUST_NOTE,
    components_report,
    horizontal_ellipse,
    pose_uncertainty,
    uncertainty_report,
)

__all__ = [
    "TRUST_NOTE",
    "horizontal_ellipse",
    "components_report",
    "pose_uncertainty",
    "uncertainty_report",
]
