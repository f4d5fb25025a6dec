"""Shared, session-scoped ground truth: one small synthetic scene for all tests.

The ``small`` preset (8 images, 2 per direction) at a reduced resolution
(600 x 400 px, so GSD ~0.5 m) so that it renders in a few seconds in-process.
"""

from __future__ import annotations

import hashlib
import os
import shutil
from pathlib import Path

import cv2
import pytest

import obliq_colmap
from obliq_colmap.synthetic import generate_scene, load_scene, preset
from obliq_colmap.threads import limit_threads

if os.environ.get("PYTEST_XDIST_WORKER"):
    # One test per core (``pytest -n 2``): each worker's BLAS and OpenCV
    # threads would otherwise compete for both cores.
    limit_threads()

#: Width of the test images (px); the field of view is the preset's.
SMALL_WIDTH_PX = 600
SMALL_SEED = 7


@pytest.fixture(scope="session")
def small_options():
    """Options of the shared small scene."""
    return preset("small", image_width_px=SMALL_WIDTH_PX)


def _source_digest() -> str:
    """Digest of the package's sources: a cached scene is reused only by
    the code that generated it."""
    root = Path(obliq_colmap.__file__).resolve().parent
    h = hashlib.sha1()
    for f in sorted(root.rglob("*.py")):
        h.update(f.relative_to(root).as_posix().encode())
        h.update(f.read_bytes())
    return h.hexdigest()[:16]


@pytest.fixture(scope="session")
def small_scene_path(tmp_path_factory, small_options, pytestconfig):
    """Path of a generated ``small`` scene folder (8 images, 600 x 400 px).

    Generating it takes ~15 s; a copy is kept in pytest's cache under the
    digest of the package's sources (so any change to the code generates it
    again) and each session works on its own copy of that."""
    cv2.setNumThreads(1)
    path = tmp_path_factory.mktemp("synthetic") / "small"
    key = f"small_w{SMALL_WIDTH_PX}_s{SMALL_SEED}_{_source_digest()}"
    cache = getattr(pytestconfig, "cache", None)  # None: -p no:cacheprovider
    store = cache.mkdir("scenes") if cache is not None else None
    if store is not None and (store / key / "scene.json").is_file():
        shutil.copytree(store / key, path)
        return path
    generate_scene(
        path,
        small_options,
        seed=SMALL_SEED,
        show_progress=False,
        num_workers=1,
        preset="small",
    )
    if store is not None:
        # whole or not at all: a copy renamed into place; older code's scenes go
        partial = store / f"{key}.{os.getpid()}.partial"
        shutil.copytree(path, partial)
        for old in store.iterdir():
            if old.name != key and not old.name.endswith(".partial"):
                shutil.rmtree(old, ignore_errors=True)
        try:
            partial.rename(store / key)
        except OSError:  # another session stored it first
            shutil.rmtree(partial, ignore_errors=True)
    return path


@pytest.fixture(scope="session")
def small_scene(small_scene_path):
    """The small scene read back with :func:`load_scene` (city rebuilt)."""
    return load_scene(small_scene_path)
