"""Prior poses in the formats users have, and export of result models.

Readers (:func:`read_priors`) turn a COLMAP model, a COLMAP database's pose
priors, an exterior-orientation (omega, phi, kappa) text file or ODM's
``geo.txt`` into the same :class:`~obliq_colmap.colmap_io.Block` in the
map's frame; :mod:`obliq_colmap.priors.export` writes a result model back
as absolute coordinates, OPK text or a COLMAP text model.
"""

from obliq_colmap.priors.export import export_model
from obliq_colmap.priors.opk import cam_from_world_from_opk, opk_from_cam_from_world
from obliq_colmap.priors.options import PriorsOptions
from obliq_colmap.priors.read import prior_format, read_priors

__all__ = [
    "PriorsOptions",
    "cam_from_world_from_opk",
    "export_model",
    "opk_from_cam_from_world",
    "prior_format",
    "read_priors",
]
