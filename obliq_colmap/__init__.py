"""obliq-colmap: register oblique aerial images to a cadastral map, output COLMAP.

The package is organised as one module per pipeline stage (see README.md):
``cadastre`` (footprints), ``lines`` and ``vanishing`` (stage 1),
``registration`` (stage 2), ``facades`` and ``bundle`` (stage 3), with
``colmap_io`` for models, ``synthetic`` for ground-truth scenes and
``evaluate`` for measuring results against ground truth.
"""

__version__ = "0.1.0"
