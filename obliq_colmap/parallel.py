"""One process pool for every per-image loop, with a progress bar.

Workers are started with ``spawn`` (they must not inherit the parent's BLAS
and OpenCV threads) and run with one BLAS and one OpenCV thread each, so that
N workers use N cores. With one worker the work runs in the calling process,
which keeps tracebacks and profiles simple.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from concurrent.futures import ProcessPoolExecutor
from multiprocessing import get_context
from typing import Any


def available_cores() -> int:
    """The cores this process may run on (its affinity mask, not the machine's)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def _start_worker(initializer: Callable | None, initargs: tuple) -> None:
    import cv2
    from threadpoolctl import threadpool_limits

    cv2.setNumThreads(1)  # one process per core; no oversubscription
    _LIMITS.append(threadpool_limits(1))
    if initializer is not None:
        initializer(*initargs)


#: The worker's thread limits, kept alive for the process's life.
_LIMITS: list[Any] = []


class WorkerPool:
    """Map a function over items in ``num_workers`` processes, in order.

    Parameters
    ----------
    num_workers : processes; 1 runs everything in the calling process.
    initializer, initargs : run once in each worker process (per-process
        state such as the cadastre).
    local_initializer : run once in the calling process when
        ``num_workers`` is 1 (None: ``initializer(*initargs)``), e.g. to hand
        over an object already loaded instead of loading it again.
    progress : show a tqdm bar per :meth:`map`.
    unit : the bar's unit.

    Use as a context manager; leaving it shuts the workers down and cancels
    what has not started (an interrupt leaves no worker behind).
    """

    def __init__(
        self,
        num_workers: int,
        initializer: Callable | None = None,
        initargs: tuple = (),
        *,
        local_initializer: Callable[[], None] | None = None,
        progress: bool = True,
        unit: str = "img",
    ) -> None:
        self.num_workers = max(1, int(num_workers))
        self.progress = progress
        self.unit = unit
        self.pool: ProcessPoolExecutor | None = None
        if self.num_workers > 1:
            self.pool = ProcessPoolExecutor(
                self.num_workers,
                mp_context=get_context("spawn"),
                initializer=_start_worker,
                initargs=(initializer, initargs),
            )
        elif local_initializer is not None:
            local_initializer()
        elif initializer is not None:
            initializer(*initargs)

    def map(self, fn: Callable, items: Sequence, desc: str) -> list:
        """``[fn(item) for item in items]``, computed by the workers."""
        from tqdm import tqdm

        bar = tqdm(
            total=len(items), desc=desc, unit=self.unit, disable=not self.progress
        )
        try:
            if self.pool is None:
                out = []
                for item in items:
                    out.append(fn(item))
                    bar.update()
                return out
            futures = [self.pool.submit(fn, item) for item in items]
            for f in futures:
                f.add_done_callback(lambda _: bar.update())
            return [f.result() for f in futures]
        finally:
            bar.close()

    def close(self) -> None:
        if self.pool is not None:
            self.pool.shutdown(cancel_futures=True)
            self.pool = None

    def __enter__(self) -> WorkerPool:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
