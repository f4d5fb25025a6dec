"""One process pool for every per-image loop, with a progress bar.

Workers are started with ``spawn`` (they must not inherit the parent's BLAS
and OpenCV threads) and run with one BLAS and one OpenCV thread each, so that
N workers use N cores. With one worker the work runs in the calling process,
which keeps tracebacks and profiles simple. With a Dask scheduler
(:mod:`obliq_colmap.dask_pool`) the same work runs on a Dask cluster.

Results never depend on where an item runs: the per-image work seeds its
random streams with :func:`image_seed`.
"""

from __future__ import annotations

import hashlib
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ProcessPoolExecutor
from contextlib import contextmanager
from multiprocessing import get_context
from typing import Any

from obliq_colmap.errors import InputError
from obliq_colmap.threads import limit_threads


def available_cores() -> int:
    """The cores this process may run on (its affinity mask, not the machine's)."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # not on Linux
        return max(1, os.cpu_count() or 1)


def image_seed(name: str, seed: int = 0) -> int:
    """A random seed for one image: a stable hash of its name mixed with the
    user's ``seed`` (Python's ``hash`` differs between processes)."""
    digest = hashlib.blake2b(f"{int(seed)}\x00{name}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") >> 1  # 63 bits: a valid numpy seed


def _start_worker(initializer: Callable | None, initargs: tuple, parent: int) -> None:
    # Ctrl-C reaches the whole process group; the calling process answers it
    # (it cancels what has not started and joins the workers), so a worker
    # ignores it instead of printing its own traceback. It was started with
    # SIGINT blocked (:func:`_sigint_blocked`): one that came while it was
    # still importing is pending, and ignoring it before unblocking drops it.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    _exit_with_parent(parent)
    limit_threads()
    if initializer is not None:
        initializer(*initargs)


def _exit_with_parent(parent: int, poll_s: float = 1.0) -> None:
    """End this worker when ``parent``, the process that started it, is
    gone (killed without a chance to shut its pool down, e.g. SIGKILL): an
    idle worker would wait on its pipe for ever, holding its memory. The
    parent's pid comes from the parent: one killed while this worker was
    still importing has already handed it to another."""

    def watch() -> None:
        while os.getppid() == parent:
            time.sleep(poll_s)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


@contextmanager
def _sigint_blocked() -> Iterator[None]:
    """SIGINT held back in the calling thread while workers are spawned.

    A spawned worker inherits the signal mask, so a Ctrl-C that arrives while
    it imports (before :func:`_start_worker` runs) waits instead of raising a
    KeyboardInterrupt with a traceback in it; the calling process gets its
    own pending Ctrl-C when the block ends. Only the main thread receives
    SIGINT, so elsewhere nothing is blocked.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


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
    progress : show a tqdm bar per :meth:`map` (None: only on a terminal).
    unit : the bar's unit.
    dask_scheduler : run on a Dask cluster instead: a scheduler's address,
        or ``local`` for a LocalCluster of ``num_workers`` one-thread
        processes (:class:`~obliq_colmap.dask_pool.DaskRunner`).

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
        progress: bool | None = True,
        unit: str = "img",
        dask_scheduler: str | None = None,
    ) -> None:
        self.num_workers = max(1, int(num_workers))
        self.progress = progress
        self.unit = unit
        self.pool: ProcessPoolExecutor | None = None
        self.dask: Any = None
        if dask_scheduler:
            self.dask = _dask_runner(
                dask_scheduler, self.num_workers, initializer, initargs
            )
        elif self.num_workers > 1:
            self.pool = ProcessPoolExecutor(
                self.num_workers,
                mp_context=get_context("spawn"),
                initializer=_start_worker,
                initargs=(initializer, initargs, os.getpid()),
            )
        elif local_initializer is not None:
            local_initializer()
        elif initializer is not None:
            initializer(*initargs)

    def map(self, fn: Callable, items: Sequence, desc: str) -> list:
        """``[fn(item) for item in items]``, computed by the workers."""
        from tqdm import tqdm

        disable = None if self.progress is None else not self.progress
        bar = tqdm(total=len(items), desc=desc, unit=self.unit, disable=disable)
        try:
            if self.dask is not None:
                return self.dask.map(fn, items, bar.update)
            if self.pool is None:
                out = []
                for item in items:
                    out.append(fn(item))
                    bar.update()
                return out
            # ProcessPoolExecutor spawns its workers as items are submitted.
            with _sigint_blocked():
                futures = [self.pool.submit(fn, item) for item in items]
            for f in futures:
                f.add_done_callback(lambda _: bar.update())
            return [f.result() for f in futures]
        finally:
            bar.close()

    def close(self) -> None:
        if self.dask is not None:
            self.dask.close()
            self.dask = None
        if self.pool is not None:
            self.pool.shutdown(cancel_futures=True)
            self.pool = None

    def __enter__(self) -> WorkerPool:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _dask_runner(
    scheduler: str, num_workers: int, initializer: Callable | None, initargs: tuple
) -> Any:
    """A :class:`~obliq_colmap.dask_pool.DaskRunner`, or an InputError naming
    the extra to install when Dask's distributed scheduler is missing."""
    try:
        from obliq_colmap.dask_pool import DaskRunner
    except ImportError as exc:
        raise InputError(
            None,
            f"--dask_scheduler needs Dask's distributed scheduler ({exc.name} is "
            "not installed): pip install 'obliq-colmap[dask]'",
        ) from exc
    return DaskRunner(scheduler, num_workers, initializer, initargs)
