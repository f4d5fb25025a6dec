"""The per-image work runs the same wherever it runs: one process, a process
pool, a Dask cluster (issue 29)."""

from __future__ import annotations

import dataclasses
import sys
from pathlib import Path

import numpy as np
import pytest

from obliq_colmap.errors import InputError
from obliq_colmap.parallel import WorkerPool, image_seed
from obliq_colmap.pipeline import PipelineOptions, load_inputs, run_register

SAMPLE = Path(__file__).resolve().parents[1] / "data_samples" / "oblique_small"


def test_image_seed_is_stable_and_depends_on_name_and_seed():
    # A fixed value: the seed must not change between processes or runs
    # (Python's own str hash is salted per process).
    assert image_seed("N_00.jpg", 0) == image_seed("N_00.jpg", 0)
    seeds = {image_seed(n, s) for n in ("N_00.jpg", "N_01.jpg") for s in (0, 1)}
    assert len(seeds) == 4
    assert all(0 <= s < 2**63 for s in seeds)
    np.random.default_rng(max(seeds))  # a valid numpy seed


def test_image_seed_is_the_same_in_another_process():
    with WorkerPool(2, progress=False) as pool:
        remote = pool.map(image_seed, ["a.jpg", "b/c.jpg"], "seeds")
    assert remote == [image_seed("a.jpg"), image_seed("b/c.jpg")]


def test_an_image_registers_the_same_under_another_id():
    """Its random streams follow its name, not its id (which depends on the
    priors model): the same image under two ids gives the same result."""
    from obliq_colmap.pipeline.inputs import image_tasks
    from obliq_colmap.pipeline.workers import initial_image, worker_pool

    options = PipelineOptions(num_workers=1, progress=False)
    inputs = load_inputs(
        SAMPLE / "images", SAMPLE / "cadastre.geojson", SAMPLE / "priors", options
    )
    task = image_tasks(inputs, options)[0]
    moved = dataclasses.replace(task, image_id=task.image_id + 1000)
    with worker_pool(1, (), inputs.cadastre, progress=False) as pool:
        a, b = pool.map(initial_image, [task, moved], "images")
    assert a.registered and b.registered
    for pose in (a.registration.cam_from_world, b.registration.cam_from_world):
        assert pose is not None
    np.testing.assert_array_equal(_matrix(a), _matrix(b))
    assert a.registration.num_inliers == b.registration.num_inliers


def test_a_missing_dask_names_the_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "distributed", None)  # import fails
    monkeypatch.delitem(sys.modules, "obliq_colmap.dask_pool", raising=False)
    with pytest.raises(InputError, match=r"obliq-colmap\[dask\]"):
        WorkerPool(2, dask_scheduler="local", progress=False)


def _matrix(outcome) -> np.ndarray:
    """(3, 4) [R | t] of an outcome's registration."""
    pose = outcome.registration.cam_from_world
    return np.c_[pose.rotation, pose.translation]


def _poses(run) -> dict[str, np.ndarray]:
    return {o.name: _matrix(o) for o in run.outcomes.values() if o.registered}


@pytest.mark.slow
def test_one_worker_two_workers_and_dask_give_identical_models():
    pytest.importorskip("distributed")
    runs = {}
    for key, workers, dask in (("1", 1, None), ("2", 2, None), ("dask", 2, "local")):
        options = PipelineOptions(
            stop_after="initial",
            num_workers=workers,
            dask_scheduler=dask,
            progress=False,
        )
        runs[key] = run_register(
            SAMPLE / "images", SAMPLE / "cadastre.geojson", SAMPLE / "priors", options
        )
    reference = _poses(runs["1"])
    assert len(reference) >= 14  # the sample registers (16/16 today)
    for key in ("2", "dask"):
        poses = _poses(runs[key])
        assert poses.keys() == reference.keys(), key
        for name, pose in reference.items():
            np.testing.assert_array_equal(poses[name], pose, err_msg=key)
