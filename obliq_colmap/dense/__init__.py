"""Dense-matching export (issue 28, item 2): a COLMAP MVS workspace from a
registration, behind ``obliq-colmap export_dense``.

Modules, in reading order: ``options`` (:class:`DenseOptions`),
``mvs_rules`` (what COLMAP's ``patch_match_stereo`` derives from the sparse
model: per-image depth ranges and source images, re-implemented on arrays so
that the workspace can be checked without a GPU), ``support`` (observations
of the block's points in the frustum of an image with too few of its own),
``config`` (patch-match.cfg, fusion.cfg and the run scripts), ``check``
(a written workspace checked with those rules), ``workspace``
(:func:`export_dense`: undistortion with pycolmap, the stereo configuration,
``georef.json`` and ``dense.json``).
"""

from obliq_colmap.dense.options import DenseOptions
from obliq_colmap.dense.workspace import DENSE_REPORT_FILE, export_dense

__all__ = ["DENSE_REPORT_FILE", "DenseOptions", "export_dense"]
