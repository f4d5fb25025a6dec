"""Second workflow (MetropoGIS): bring an existing COLMAP SfM model onto the map.

Stages, in the order the pipeline runs them (issue 27):

1. ``vertical``: the model's up direction from the images' vertical
   vanishing points (stage 1 with a terrestrial prior), and the rotation
   that makes the model upright.
2. ``similarity``: the remaining similarity (scale, heading, translation)
   from control points: closed form with two, robust least squares with
   three or more.
3. ``automatic``: without control points, the block's 5-DOF similarity
   from the cadastre (corner-to-vertical-line correspondences of all
   images through stage 2's RANSAC).
4. ``block``: the bundle block adjustment (SfM tracks, control points,
   vertical VPs, cadastral lines) in the project's bundle.
5. ``run``: :func:`georegister`, the whole job behind
   ``obliq-colmap georegister``.
"""
