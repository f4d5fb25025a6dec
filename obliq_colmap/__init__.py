"""obliq-colmap: register oblique aerial images to a cadastral map, output COLMAP.

A package per stage, imports in one direction (cli -> pipeline -> stages ->
geometry); docs/DESIGN.md describes the system and its conventions:

- ``cadastre``: the map's footprints -> corners, edges, per-camera visibility;
- ``lines``, ``vanishing``: stage 1, line segments and the vertical vanishing
  point with its VP-constrained segments;
- ``registration``: stage 2, each image's pose against the map by RANSAC over
  corner-to-vertical-line pairs;
- ``adjustment`` (with the solver in ``bundle``): stage 3, facade edges, their
  tracks and one bundle over all cameras, and the verdicts on its images;
- ``pipeline``: chains the stages over a block (``run_register``);
  ``state`` holds the run state the stages and the pipeline share;
- ``colmap_io``, ``files``, ``parallel``, ``geometry``, ``errors``: models,
  atomic writing, the worker pool, cameras and poses, input errors;
- ``evaluate``: a result against ground truth; ``synthetic``: scenes with
  known cameras; ``cli``: the ``obliq-colmap`` command.
"""

__version__ = "0.1.0"
