"""A deterministic synthetic oblique city with exact ground truth.

The ground-truth instrument of the project: a city (terrain, streets,
buildings with procedural facades, unmapped clutter), a four-headed oblique
camera flying a grid over it, rendered images, a cadastre with realistic
discrepancies, rough priors and the exact COLMAP model.

Public API
----------
SceneOptions, PRESETS, preset
    All parameters of a scene (units documented per field) and named presets
    (``small``: 8 images, ``paper``: 36 images, ``hard``).
generate_scene(output_path, options, *, seed, show_progress=True, num_workers=None)
    Write a scene folder atomically (images/, cadastre.geojson, priors/, gt/,
    gt_buildings.json, scene.json).
build_city(options, seed) -> City
    The 3D city, rebuilt deterministically (local frame).
load_scene(path) -> SyntheticScene
    Read a scene folder back and rebuild its city (no re-rendering).
render_image(city, camera, pose, options) -> (image, depth, buffers)
    Render one image (pose in the city's LOCAL frame).
true_vertical_edges(scene, image_name) -> dict
    Visible parts of all true vertical edges as (M, 2, 2) pixel segments.
true_vertical_vp(scene, image_name) -> (3,) array
    The true vertical vanishing point (homogeneous, undistorted pixels).
"""

from obliq_colmap.synthetic.city import (
    Building,
    City,
    build_city,
    corners,
    vertical_edges,
)
from obliq_colmap.synthetic.options import PRESETS, SceneOptions, preset
from obliq_colmap.synthetic.render import render_depth, render_image
from obliq_colmap.synthetic.scene_io import (
    SyntheticScene,
    generate_scene,
    load_scene,
    true_vertical_edges,
    true_vertical_vp,
)

__all__ = [
    "PRESETS",
    "Building",
    "City",
    "SceneOptions",
    "SyntheticScene",
    "build_city",
    "corners",
    "generate_scene",
    "load_scene",
    "preset",
    "render_depth",
    "render_image",
    "true_vertical_edges",
    "true_vertical_vp",
    "vertical_edges",
]
