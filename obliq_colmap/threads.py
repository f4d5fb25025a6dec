"""One BLAS and one OpenCV thread per worker process (the process pool's
and the Dask workers' start)."""

from __future__ import annotations

from typing import Any

__all__ = ["limit_threads"]

# The limits live as long as the process: kept referenced here.
_LIMITS: list[Any] = []


def limit_threads() -> None:
    """One BLAS and one OpenCV thread in this process, for its life."""
    import cv2
    from threadpoolctl import threadpool_limits

    cv2.setNumThreads(1)  # one process per core; no oversubscription
    _LIMITS.append(threadpool_limits(1))
