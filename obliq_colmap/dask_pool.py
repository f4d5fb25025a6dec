"""The per-image work on a Dask cluster (``register --dask_scheduler``).

The workers read the images and the map from a file system they share with
the caller (the tasks carry paths, not pixels) and send back plain picklable
results. ``local`` starts a LocalCluster of one-thread worker processes on
this machine. Needs the optional extra ``dask`` (``dask[distributed]``).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from typing import Any

import distributed
from distributed.diagnostics.plugin import WorkerPlugin

from obliq_colmap.errors import InputError

__all__ = ["DaskRunner"]

logger = logging.getLogger(__name__)


class _WorkerSetup(WorkerPlugin):
    """Run in each Dask worker when it starts or joins: one BLAS and OpenCV
    thread, then the pool's initializer (e.g. load the map once per worker)."""

    def __init__(self, initializer: Callable | None, initargs: tuple) -> None:
        self.initializer = initializer
        self.initargs = initargs

    def setup(self, worker: Any) -> None:
        from obliq_colmap.threads import limit_threads

        limit_threads()
        if self.initializer is not None:
            self.initializer(*self.initargs)


class DaskRunner:
    """Map functions over items on a Dask cluster, results in order.

    Parameters
    ----------
    scheduler : address of a running scheduler (``tcp://host:8786``), or
        ``local`` for a LocalCluster of ``num_workers`` processes with one
        thread each.
    num_workers : processes of a LocalCluster (unused with an address).
    initializer, initargs : run once in each worker (see :class:`_WorkerSetup`).
    """

    def __init__(
        self,
        scheduler: str,
        num_workers: int,
        initializer: Callable | None = None,
        initargs: tuple = (),
    ) -> None:
        self.cluster = None
        try:
            if scheduler == "local":
                self.cluster = distributed.LocalCluster(
                    n_workers=max(1, num_workers),
                    threads_per_worker=1,
                    processes=True,
                    dashboard_address=None,
                    silence_logs=logging.WARNING,
                )
                self.client = distributed.Client(self.cluster)
            else:
                self.client = distributed.Client(scheduler, timeout="30s")
        except OSError as exc:
            if self.cluster is not None:
                self.cluster.close()
            raise InputError(
                None, f"--dask_scheduler {scheduler}: cannot connect: {exc}"
            ) from exc
        self.client.register_plugin(
            _WorkerSetup(initializer, initargs), name="obliq-colmap-setup"
        )
        logger.info(
            "Dask scheduler %s: %d workers",
            self.client.scheduler.address,
            len(self.client.scheduler_info()["workers"]),
        )

    def map(self, fn: Callable, items: Sequence, on_done: Callable[[], None]) -> list:
        """``[fn(item) for item in items]`` on the cluster; ``on_done`` is
        called once per finished item (the progress bar)."""
        futures = self.client.map(fn, list(items), pure=False)
        try:
            for _ in distributed.as_completed(futures):
                on_done()
            return self.client.gather(futures)
        finally:
            self.client.cancel(futures)

    def close(self) -> None:
        self.client.close()
        if self.cluster is not None:
            self.cluster.close()
