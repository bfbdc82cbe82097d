"""Layers planned ahead, side by side (issue 28: wall time): what a layer's beads are does not
depend on where the torch is, only their order does (planner.layer.layer_groups / placed).

Every layer's islands (and its memo key) are made first; the layers the memo will not have are
then planned on worker threads, a few layers ahead of the plan, while the plan orders, welds and
judges each layer in turn as before. GEOS and numpy release the GIL, so two cores plan about 1.5x
faster; each layer is planned by the same pure function from the same inputs, so the job is the
same byte for byte whatever the threads (tests/planner/test_planner_speed.py). On one core, or for a
layer or two, nothing runs on a thread.
"""
from __future__ import annotations

import math
import os
from collections import deque
from typing import TYPE_CHECKING, Any, Callable, Generic, Protocol, Sequence, TypeVar

from shapely.geometry import Polygon

from planner.layer import LayerCtx, LayerGroups, layer_groups
from planner.nearnet import grow_layers, snapped, supported
from planner.regions import islands
from planner.slicer import LayerSlice

if TYPE_CHECKING:
    from concurrent.futures import Future, ThreadPoolExecutor

Key = tuple[bytes, int, bool]
Prepared = tuple[list[Polygon], list[Polygon], Key]  # net islands, grown islands, memo key

T = TypeVar("T")
T_co = TypeVar("T_co", covariant=True)

MIN_THREADED = 8  # layers to plan (memo misses) below which no thread is started


def workers() -> int:
    """Threads to plan on: the cores this process may use (at most 4)."""
    try:
        n = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        n = os.cpu_count() or 1
    return max(1, min(n, 4))


def _bead_area(ctx: LayerCtx) -> float:
    """The footprint of the shortest, narrowest legal bead: support stock apart from a layer's
    region smaller than it is not built (planner.nearnet.supported)."""
    lo = ctx.widths.lo
    return lo * ctx.min_length + 0.25 * math.pi * lo * lo


class Later(Protocol[T_co]):
    """A value being computed (a Future) or already there (Done)."""

    def result(self) -> T_co: ...


class Done(Generic[T]):
    def __init__(self, value: T) -> None:
        self.value = value

    def result(self) -> T:
        return self.value


class Ahead:
    """Each layer's islands and key (`prepared`) and its beads before ordering (`groups`)."""

    def __init__(self, slices: Sequence[LayerSlice], tops: Sequence[bool], ctx: LayerCtx,
                 key: Callable[[list[Polygon], int, bool], Key], misses: Callable[[list[Key]], list[bool]],
                 threads: int | None = None) -> None:
        self.ctx = ctx
        self._key = key
        self.threads = workers() if threads is None else threads
        self._pool: ThreadPoolExecutor | None = None
        # in turn: islands are cheap, and a tall prism's many layers would only pass the GIL around
        nets = [islands([c.points for c in sl.contours if c.closed], simplify_mm=0.005 * ctx.width) for sl in slices]
        grown = supported(grow_layers(nets, ctx.allowance, ctx.height), ctx.support_mm, ctx.allowance,
                          _bead_area(ctx))
        if ctx.allowance > 0:   # unions of offsets: snapped onto a 1e-6 mm grid, valid for every overlay after
            grown = [snapped(g) for g in grown]
        self.prepared: list[Prepared] = [(n, g, key(g, sl.index, top)) for n, g, sl, top in zip(nets, grown, slices, tops)]
        miss = misses([p[2] for p in self.prepared])
        self._todo = deque(i for i, m in enumerate(miss) if m)
        self._running: dict[int, Future[LayerGroups]] = {}
        if self.threads > 1 and len(self._todo) >= MIN_THREADED:
            # only a plan with layers to share starts threads (concurrent.futures: start-up time)
            from concurrent.futures import ThreadPoolExecutor

            self._pool = ThreadPoolExecutor(self.threads, thread_name_prefix="plan")
        self._fill()

    def _fill(self) -> None:
        """Keep a few layers planning ahead of the one the plan is at (bounded memory)."""
        while self._pool is not None and self._todo and len(self._running) < 2 * self.threads + 1:
            i = self._todo.popleft()
            self._running[i] = self._pool.submit(layer_groups, self.prepared[i][1], i, self.ctx)

    def groups(self, index: int) -> LayerGroups:
        """Layer `index`'s beads before ordering: planned ahead, or now."""
        fut = self._running.pop(index, None)
        if fut is None:
            if self._todo and self._todo[0] == index:
                self._todo.popleft()
            out = layer_groups(self.prepared[index][1], index, self.ctx)
        else:
            out = fut.result()
        self._fill()
        return out

    @property
    def depth(self) -> int:
        """Layers the plan may start before it finishes the first of them (0: one by one)."""
        return 2 * self.threads if self._pool is not None else 0

    def later(self, fn: Callable[..., T], *args: Any) -> Later[T]:
        """fn(*args) on a worker thread, or now when there is none."""
        if self._pool is None:
            return Done(fn(*args))
        return self._pool.submit(fn, *args)

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def __enter__(self) -> Ahead:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()
