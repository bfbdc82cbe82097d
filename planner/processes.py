"""Per-layer work sent to worker processes (issue 40 item 3: the 2 cores), docs/plan-speed.md.

What a layer's feed-forward levels (planner/feedforward.py, `level_layer`) depends only on that
layer's welded passes, and most of it is numpy on small arrays, which holds the GIL: threads would
take turns at it. So a plan with enough layers to level sends each layer's call to a process pool
as soon as the layer is welded, and takes the results in layer order.

The workers are forked, and only from a process that has no other thread yet (`cell plan`, before
the plan starts its own threads): a fork of a threaded process can inherit a lock another thread
held. A plan called beside other threads (the controller's device loop) levels its layers in turn,
as before. Forked workers import nothing and do not run the caller's `__main__` again (a spawned
or forkserver worker would).

Only on a host with a core to spare (`spare_cores`): on a loaded one the workers wait for a core
between layers and the plan takes longer than in one process. The plan never waits for an idle
pool: a call still queued when its layer is due is taken back and run in the planning process
itself (`Stealable`). The same pure function on the same inputs: the
job is the same byte for byte with or without the pool.
"""
from __future__ import annotations

import os
import threading
from typing import TYPE_CHECKING, Any, Callable, Generic, TypeVar

if TYPE_CHECKING:
    from concurrent.futures import Future, ProcessPoolExecutor

T = TypeVar("T")

MIN_LAYERS = 40  # layers to level below which no process is started (its start-up is ~0.2 s of CPU)


def spare_cores(n: int) -> bool:
    """True when the host has cores to spare: its load average (1 min) below `n` - 0.5. On a host
    whose cores are all taken, the workers only wait for a core between the layers (measured at load
    12 on 2 cores: the box at 8 mm 14 -> 23 s wall, +30 % CPU), so the plan stays in one process."""
    try:
        return os.getloadavg()[0] < n - 0.5
    except OSError:
        return False


class Stealable(Generic[T]):
    """fn(*args) on a worker process, or here when the worker has not started it yet."""

    def __init__(self, fut: Future[T] | None, fn: Callable[..., T], args: tuple[Any, ...]) -> None:
        self._fut, self._fn, self._args = fut, fn, args

    def result(self) -> T:
        if self._fut is None or self._fut.cancel():
            return self._fn(*self._args)
        return self._fut.result()


class Processes:
    """A pool of `n` forked worker processes (none when n < 2 or other threads run: `n` is then 0)."""

    def __init__(self, n: int) -> None:
        self._pool: ProcessPoolExecutor | None = None
        if n >= 2 and threading.active_count() == 1 and spare_cores(n):
            # only a plan with layers to level starts processes (multiprocessing: start-up time)
            import multiprocessing
            from concurrent.futures import ProcessPoolExecutor

            self._pool = ProcessPoolExecutor(n, mp_context=multiprocessing.get_context("fork"))
            self._pool.submit(int).result()  # every worker forked now, before any thread starts
        self.n = n if self._pool is not None else 0

    def submit(self, fn: Callable[..., T], *args: Any) -> Stealable[T]:
        return Stealable(None if self._pool is None else self._pool.submit(fn, *args), fn, args)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def __enter__(self) -> Processes:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
