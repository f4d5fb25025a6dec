"""Shared, session-scoped ground truth: one small synthetic scene for all tests.

The ``small`` preset (8 images, 2 per direction) at a reduced resolution
(600 x 400 px, so GSD ~0.5 m) so that it renders in a few seconds in-process.
"""

from __future__ import annotations

import cv2
import pytest

from obliq_colmap.synthetic import generate_scene, load_scene, preset

#: Width of the test images (px); the field of view is the preset's.
SMALL_WIDTH_PX = 600
SMALL_SEED = 7


@pytest.fixture(scope="session")
def small_options():
    """Options of the shared small scene."""
    return preset("small", image_width_px=SMALL_WIDTH_PX)


@pytest.fixture(scope="session")
def small_scene_path(tmp_path_factory, small_options):
    """Path of a generated ``small`` scene folder (8 images, 600 x 400 px)."""
    cv2.setNumThreads(1)
    path = tmp_path_factory.mktemp("synthetic") / "small"
    generate_scene(
        path,
        small_options,
        seed=SMALL_SEED,
        show_progress=False,
        num_workers=1,
        preset="small",
    )
    return path


@pytest.fixture(scope="session")
def small_scene(small_scene_path):
    """The small scene read back with :func:`load_scene` (city rebuilt)."""
    return load_scene(small_scene_path)
