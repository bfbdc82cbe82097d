"""The deposit's shape: a height map in the substrate frame (docs/process-physics.md).

A dense grid of square cells (`cell_mm`, at most 0.5 mm) that grows as metal lands further out.
Each cell holds the top z of the deposit (NaN where nothing was deposited); under it lies the
substrate, whose top comes from a callback (the robot's plane z = 0, the CNC's workpiece mesh).

A bead is laid along a segment in chunks of about 1 mm. Each chunk pours its metal (area × the
bead length its cells stand for; nothing is lost or counted twice) into the cells of its footprint
(distance to the segment ≤ w/2, the chunk by the cell's projection on the segment). A bead is one
pool from its arc start to its arc end, continuous across the segments (robot moves) it is laid
in: it has a round start and a round end at those two places only; at a joint between two of its
segments only the outside of a turn gets the round end's cells (`lay_steps`).
The liquid fills the lowest cells first up to a level `c` and is held by Ding's parabola of the
bead's width (its distance d to the segment: round ends; where the footprints of consecutive
segments overlap, the max keeps the metal from counting twice), resting on the surface at the
centre line:

    new = max(old, min(c, base + H·(1 − (2d/w)²)))   with H = 1.5·area/w

On a flat plate this is exactly Ding's parabola of that area; next to a bead of the same layer
the metal first fills the valley (the tangent-overlap idea), so overlapped beads build a flat
layer whose thickness is the metal over the step-over, and a stacked wall rises area/w a layer.
Cells touched by the bead being laid keep their surface from before it (`surface_before`), so
the torch sees the ground it rests on, not its own bead.

Over a free edge (a cell with nothing under it and nothing laid yet) the pool hangs on the side
face, held by surface tension, down to its own height H below the bead's base: the metal fills
from there, so a first bead laid half over an edge slumps (the hanging half takes its share
first) and the beads laid on it stand as on any surface (docs/process-physics.md "Free edges").
"""
from __future__ import annotations

import math
from collections import deque
from typing import Callable, Generator

import numpy as np
from numpy.typing import NDArray

from sims.pour import Chunk, FloatArray, Laid, alone_rise, finish, frame, merge_cells, metal_per_cell, pour_level

Substrate = Callable[[FloatArray, FloatArray], FloatArray]
Scale = Callable[[float, float, float], float]    # (x, y, mm along the segment) -> metal factor
CHUNK_MM = 1.0
_GROW = 64          # cells of margin added on every side when the grid grows
TAIL_MM = 40.0      # the bead's last centre cells kept for its end (sag)
_OFF_PART = -1e8    # a substrate top below this: nothing under the cell (off the part's edge)
JOINT_MM = 1e-3     # a segment starting this near the bead's last end goes on from it
POOL_WIDTHS = 2.0   # a pool's length behind the arc, in bead widths: its metal levels out in it


def flat_substrate(xs: FloatArray, ys: FloatArray) -> FloatArray:
    """The robot's substrate: the plane z = 0 of its frame."""
    return np.zeros(np.shape(xs))


class HeightMap:
    """Top of the deposit per cell over a substrate; grows to wherever metal lands."""

    def __init__(self, cell_mm: float = 0.5, substrate: Substrate | None = None) -> None:
        if not 0.0 < cell_mm <= 0.5:
            raise ValueError(f"height-map cells must be at most 0.5 mm (got {cell_mm})")
        self.cell = float(cell_mm)
        self.substrate = substrate or flat_substrate
        self._i0 = self._j0 = 0                 # cell index of [0, 0]
        self.top: FloatArray = np.full((0, 0), np.nan)     # [j, i]: y rows, x columns
        self._base: FloatArray = np.full((0, 0), np.nan)   # substrate top (NaN: not asked yet)
        self._stamp = np.zeros((0, 0), dtype=np.int64)     # bead that last raised the cell
        self._before: FloatArray = np.full((0, 0), np.nan)  # its surface before that bead
        self.carved = np.zeros((0, 0), dtype=bool)        # the substrate under the cell was cut
        self.bead = 0
        self.volume_mm3 = 0.0
        self._trail: deque[tuple[float, int, int]] = deque()   # (path mm, centre cell) of this bead
        self._tail: deque[tuple[float, int, int]] = deque()    # the same, its last TAIL_MM (end sag)
        self._path = 0.0
        self._pool: deque[Chunk] = deque()    # chunks of the bead not poured yet
        self._start_open = False                # the bead's first pool not poured yet
        self._lost = 0.0                          # mm³ of this map's beads that did not fit
        self._spill = 0.0                         # cell-heights that did not fit, running on in the pool

    # -- grid ----------------------------------------------------------------------------------
    def _ensure(self, i_lo: int, i_hi: int, j_lo: int, j_hi: int) -> None:
        ny, nx = self.top.shape
        if nx and i_lo >= self._i0 and i_hi < self._i0 + nx and j_lo >= self._j0 and j_hi < self._j0 + ny:
            return
        if nx:
            i_lo, i_hi = min(i_lo, self._i0), max(i_hi, self._i0 + nx - 1)
            j_lo, j_hi = min(j_lo, self._j0), max(j_hi, self._j0 + ny - 1)
        i0, j0 = i_lo - _GROW, j_lo - _GROW
        shape = (j_hi + _GROW - j0 + 1, i_hi + _GROW - i0 + 1)
        rows = slice(self._j0 - j0, self._j0 - j0 + ny)
        cols = slice(self._i0 - i0, self._i0 - i0 + nx)

        def grown(old: FloatArray) -> FloatArray:
            new = np.full(shape, np.nan)
            new[rows, cols] = old
            return new

        stamp = np.zeros(shape, dtype=np.int64)
        stamp[rows, cols] = self._stamp
        carved = np.zeros(shape, dtype=bool)
        carved[rows, cols] = self.carved
        self.top, self._base, self._before, self._stamp = grown(self.top), grown(self._base), grown(self._before), stamp
        self.carved = carved
        self._i0, self._j0 = i0, j0

    def index(self, x: float, y: float) -> tuple[int, int]:
        return math.floor(x / self.cell), math.floor(y / self.cell)

    def _base_at(self, ii: NDArray[np.int64], jj: NDArray[np.int64]) -> FloatArray:
        """Substrate top under cells (absolute indices, inside the grid), asked once per cell."""
        r, c = jj - self._j0, ii - self._i0
        b = self._base[r, c]
        todo = np.isnan(b)
        if np.any(todo):
            xs = (ii[todo] + 0.5) * self.cell
            ys = (jj[todo] + 0.5) * self.cell
            got = np.asarray(self.substrate(xs.astype(float), ys.astype(float)), dtype=float)
            got = np.where(np.isfinite(got), got, -1e9)  # nothing under it: off the part (_pour: metal hangs)
            self._base[r[todo], c[todo]] = got
            b = self._base[r, c]
        return b

    def _surface_idx(self, ii: NDArray[np.int64], jj: NDArray[np.int64]) -> FloatArray:
        return np.fmax(self.top[jj - self._j0, ii - self._i0], self._base_at(ii, jj))

    # -- queries -------------------------------------------------------------------------------
    def deposit_top(self, x: float, y: float) -> float | None:
        """Top of the deposit at (x, y), or None where nothing was deposited."""
        self.end_bead()
        i, j = self.index(x, y)
        ny, nx = self.top.shape
        if not (0 <= i - self._i0 < nx and 0 <= j - self._j0 < ny):
            return None
        v = float(self.top[j - self._j0, i - self._i0])
        return None if math.isnan(v) else v

    def surface(self, x: float, y: float, *, before_bead: bool = False) -> float:
        """The surface at (x, y): deposit or substrate; `before_bead`: as it was before the current
        bead (else the current bead is read as ended here: `end_bead`)."""
        if not before_bead:
            self.end_bead()
        i, j = self.index(x, y)
        self._ensure(i, i, j, j)
        r, c = j - self._j0, i - self._i0
        if before_bead and self._stamp[r, c] == self.bead and self.bead:
            return float(self._before[r, c])
        ii, jj = np.array([i]), np.array([j])
        return float(self._surface_idx(ii, jj)[0])

    def deposit_tops(self, xs: FloatArray, ys: FloatArray) -> FloatArray:
        """Vectorised `deposit_top` (NaN where nothing was deposited or outside the grid)."""
        self.end_bead()
        ii = np.floor(np.asarray(xs) / self.cell).astype(np.int64) - self._i0
        jj = np.floor(np.asarray(ys) / self.cell).astype(np.int64) - self._j0
        ny, nx = self.top.shape
        ok = (ii >= 0) & (ii < nx) & (jj >= 0) & (jj < ny)
        out = np.full(np.shape(ii), np.nan)
        out[ok] = self.top[jj[ok], ii[ok]]
        return out

    def solid_tops(self, xs: FloatArray, ys: FloatArray) -> FloatArray:
        """The top the map knows at each point: the deposit's, or a cut substrate's (NaN: the
        untouched substrate, which the workpiece mesh answers)."""
        self.end_bead()
        ii = np.floor(np.asarray(xs) / self.cell).astype(np.int64) - self._i0
        jj = np.floor(np.asarray(ys) / self.cell).astype(np.int64) - self._j0
        ny, nx = self.top.shape
        ok = (ii >= 0) & (ii < nx) & (jj >= 0) & (jj < ny)
        out = np.full(np.shape(ii), np.nan)
        t = self.top[jj[ok], ii[ok]]
        cut = self.carved[jj[ok], ii[ok]]
        out[ok] = np.where(cut, np.fmax(t, self._base[jj[ok], ii[ok]]), t)
        return out

    def cut_away(self, q: FloatArray) -> bool:
        """Was the substrate at point q cut away (above a carved cell's new top)?"""
        t = self.solid_tops(np.array([q[0]]), np.array([q[1]]))[0]
        i, j = self.index(float(q[0]), float(q[1]))
        ny, nx = self.top.shape
        r, c = j - self._j0, i - self._i0
        return bool(0 <= r < ny and 0 <= c < nx and self.carved[r, c] and q[2] > t + 1e-9)

    def inside(self, q: FloatArray) -> bool:
        """Is the point inside deposited metal (below the deposit's top in a deposited cell)?"""
        t = self.deposit_tops(np.array([q[0]]), np.array([q[1]]))[0]
        return bool(np.isfinite(t) and q[2] <= t)

    def ray_hit(self, q0: FloatArray, q1: FloatArray) -> float | None:
        """Distance along q0→q1 to the first point inside deposited metal, or None."""
        self.end_bead()
        d = np.asarray(q1, dtype=float) - np.asarray(q0, dtype=float)
        length = float(np.linalg.norm(d))
        if length < 1e-12 or not self.top.size or (np.all(np.isnan(self.top)) and not self.carved.any()):
            return None
        n = max(2, int(math.ceil(length / (self.cell / 8.0))) + 1)
        s = np.linspace(0.0, length, n)
        pts = np.asarray(q0, dtype=float)[None, :] + s[:, None] * (d / length)[None, :]
        tops = self.solid_tops(pts[:, 0], pts[:, 1])
        hit = np.isfinite(tops) & (pts[:, 2] <= tops)
        if not np.any(hit):
            return None
        k = int(np.argmax(hit))
        if k == 0:
            return 0.0
        # between samples k-1 (outside) and k (inside): the top is flat over a cell, so linear is exact
        z0, z1 = pts[k - 1, 2], pts[k, 2]
        t1 = tops[k]
        if np.isfinite(tops[k - 1]) and abs(tops[k - 1] - t1) < 1e-12 and z0 != z1:
            f = (z0 - t1) / (z0 - z1)
            return float(s[k - 1] + f * (s[k] - s[k - 1]))
        return float(s[k])

    # -- deposition ----------------------------------------------------------------------------
    def new_bead(self) -> int:
        self.end_bead()
        self._start_open = True
        self.bead += 1
        self._trail.clear()
        self._tail.clear()
        self._path = 0.0
        return self.bead

    def lay(self, p0: tuple[float, float], p1: tuple[float, float], width_mm: float, area_mm2: float) -> Laid:
        """Pour a bead of `area_mm2` metal per mm, `width_mm` wide, along p0→p1 (substrate xy)."""
        return finish(self.lay_steps(p0, p1, width_mm, area_mm2))

    def lay_steps(self, p0: tuple[float, float], p1: tuple[float, float], width_mm: float, area_mm2: float,
                  chunks_per_step: int = 10, scale: Scale | None = None) -> Generator[None, None, Laid]:
        """`lay`, resumable: a yield after every `chunks_per_step` chunks (1 mm each), the same
        cells poured in the same order as in one call; the Laid is the generator's value.
        `scale(x, y, s)`: the metal of the chunk centred at (x, y), s mm along the segment, is
        `area_mm2` times it (its parabola as high in proportion).

        A bead is one pool from arc start to arc end (docs/process-physics.md "one pool per bead"):
        a segment going on from the last has no round start, the last's round end keeps only the
        cells behind it (a turn's outside); chunks wait (`Chunk`) until POOL_WIDTHS bead widths
        behind; the first and last pools pour with the round start / end (`end_bead`)."""
        a, b = np.asarray(p0, dtype=float), np.asarray(p1, dtype=float)
        d = b - a
        length = float(np.hypot(d[0], d[1]))
        if length < 1e-9 or width_mm <= 0 or area_mm2 <= 0:
            return Laid(None, 0.0)
        u = d / length
        nrm = np.array([-u[1], u[0]])
        half = width_mm / 2.0
        last = self._pool[-1] if self._pool else None
        cont = last is not None and last.at is not None and float(np.hypot(*(a - last.at))) < JOINT_MM
        if last is not None and cont:
            tn, _ = frame(last.ii, last.jj, self.cell, a, u, nrm)
            keep = ~(last.round_end & (tn >= 0.0))     # the bead goes on over the rest of its round end
            last.ii, last.jj, last.s, last.round_end = last.ii[keep], last.jj[keep], last.s[keep], last.round_end[keep]
            last.at = None
        elif self._pool:
            self._pour_pool(list(self._pool))    # a jump: the pool so far ends here
            self._pool.clear()
        lo, hi = np.minimum(a, b) - half, np.maximum(a, b) + half
        i_lo, j_lo = self.index(float(lo[0]), float(lo[1]))
        i_hi, j_hi = self.index(float(hi[0]), float(hi[1]))
        self._ensure(i_lo, i_hi, j_lo, j_hi)
        gi, gj = np.meshgrid(np.arange(i_lo, i_hi + 1, dtype=np.int64), np.arange(j_lo, j_hi + 1, dtype=np.int64))
        ii, jj = gi.ravel(), gj.ravel()
        t, s = frame(ii, jj, self.cell, a, u, nrm)
        tc = np.clip(t, 0.0, length)
        dist = np.hypot(t - tc, s)       # distance to the segment: round ends, as a pool is
        m = (dist <= half) & ~((t < 0.0) & cont)     # a bead going on has no round start
        beside = (t[m] >= 0.0) & (t[m] <= length)   # the strip beside the segment, not its round ends
        ii, jj, t, s = ii[m], jj[m], tc[m], dist[m]
        n_chunks = max(1, math.ceil(length / CHUNK_MM))
        step = length / n_chunks
        chunk = np.minimum((t / step).astype(np.int64), n_chunks - 1)
        per_cell = metal_per_cell(self.cell, a, u, nrm, length, half)
        counts = np.bincount(chunk[beside], minlength=n_chunks)
        peak = 1.5 * area_mm2 / width_mm
        cell2 = self.cell * self.cell
        carry, poured = 0.0, 0.0
        lost0 = self._lost
        for k in range(n_chunks):
            if k and k % chunks_per_step == 0:
                yield
            sel = chunk == k
            mid = a + u * (k + 0.5) * step
            f = 1.0 if scale is None else float(scale(float(mid[0]), float(mid[1]), (k + 0.5) * step))
            metal = area_mm2 * f * (counts[k] * per_cell if per_cell > 0.0 else step)
            poured += metal
            if not np.any(sel):
                carry += metal / cell2
                continue
            end = ~beside[sel] & (t[sel] >= length - 1e-12)
            self._pool.append(Chunk(ii[sel], jj[sel], s[sel], end, self.index(float(mid[0]), float(mid[1])),
                                    width_mm, peak * f, metal / cell2 + carry,
                                    b if k == n_chunks - 1 else None, self._path + (k + 0.5) * step))
            carry = 0.0
            self._drain(self._path + (k + 1) * step, width_mm * POOL_WIDTHS)
        self.volume_mm3 += poured
        self._lost += carry * cell2
        self._path += length
        while self._tail and self._tail[0][0] < self._path - TAIL_MM:
            self._tail.popleft()
        return Laid(self._rise_behind(half + self.cell), self._lost - lost0)

    def _rise_behind(self, behind_mm: float) -> float | None:
        """The bead's rise on its centre line `behind_mm` back along the path: the chunk there
        poured alone as it stands (it waits in the pool), else the latest poured one's."""
        ready = [c for c in self._pool if c.path_mm <= self._path - behind_mm and c.ii.size]   # (a turn can take all a chunk's cells)
        base = self._rest_on(ready[-1].centre) if ready else _OFF_PART
        if base <= _OFF_PART:
            return self._settled_rise(behind_mm)
        return alone_rise(ready[-1], self._surface_idx(ready[-1].ii, ready[-1].jj), base, _OFF_PART)

    def _drain(self, path_mm: float, pool_mm: float) -> None:
        """Pour the chunks the bead (now `path_mm` long) has left `pool_mm` behind, one by one; its
        first `pool_mm` (the start's pool, round start included) together once it is that long."""
        if self._start_open:
            first = [c for c in self._pool if c.path_mm < pool_mm]
            if path_mm < pool_mm or (first and first[-1].at is not None):
                return         # (a segment's last chunk waits to know whether the bead goes on)
            for _ in first:
                self._pool.popleft()
            self._pour_pool(first)
            self._start_open = False
        while self._pool and self._pool[0].path_mm < path_mm - pool_mm and self._pool[0].at is None:
            self._pour_pool([self._pool.popleft()])

    def _pour_pool(self, chunks: list[Chunk]) -> None:
        """Pour chunks as one pool: their metal together into all their cells, each cell held by the
        highest of its chunks' parabolas (what does not fit, at a turn's inside, runs on into the
        pool's next chunk; at the bead's end it is lost to the 2.5-D map)."""
        if not chunks:
            return
        iis, jjs, envs, hangs = [], [], [], []
        for c in chunks:
            iis.append(c.ii)
            jjs.append(c.jj)
            base = self._rest_on(c.centre)
            old = self._surface_idx(c.ii, c.jj)
            if base < _OFF_PART and np.any(old >= _OFF_PART):   # its centre over an edge: it rests on the edge's top
                base = float(np.max(old[old >= _OFF_PART]))
            envs.append(base + c.peak * (1.0 - (2.0 * c.s / c.width) ** 2))
            hangs.append(np.full(c.ii.size, base - c.peak))
            self._trail.append((c.path_mm, c.centre[0], c.centre[1]))
            self._tail.append(self._trail[-1])
        ii, jj, env, hang = np.concatenate(iis), np.concatenate(jjs), np.concatenate(envs), np.concatenate(hangs)
        if len(chunks) > 1 and ii.size:
            ii, jj, env, hang = merge_cells(ii, jj, env, hang)
        need = sum(c.need for c in chunks) + self._spill   # (chunks a turn left no cell of their own: it runs on)
        left, self._spill = (self._pour(ii, jj, env, hang, need) if ii.size else need), 0.0
        if self._pool:             # the pool goes on: what did not fit here runs on in it
            self._spill = left
            return
        self._lost += left * self.cell * self.cell
        self.volume_mm3 -= left * self.cell * self.cell

    def end_bead(self) -> None:
        """The bead ended (the arc went out): what waits in its pool poured together, its last
        segment's whole round end included."""
        if self._pool:
            chunks = list(self._pool)
            self._pool.clear()
            self._start_open = False
            self._pour_pool(chunks)

    def _settled_rise(self, behind_mm: float) -> float | None:
        """The bead's rise on its centre line where the pool has passed (`behind_mm` back along
        the path): the metal of later chunks no longer reaches it. None near the bead's start."""
        while len(self._trail) > 1 and self._trail[1][0] <= self._path - behind_mm:
            self._trail.popleft()
        if not self._trail or self._trail[0][0] > self._path - behind_mm:
            return None
        _, i, j = self._trail[0]
        r, c = j - self._j0, i - self._i0
        if self._stamp[r, c] != self.bead or self._before[r, c] < _OFF_PART:   # none over a free edge
            return None
        return float(self._surface_idx(np.array([i]), np.array([j]))[0] - self._before[r, c])

    def sag_end(self, direction: tuple[float, float], width_mm: float, share: float) -> float:
        """The bead just ended: when its end is open (the surface one bead half-width and two cells
        beyond it lies lower than the bead's base there plus half its rise), `share` of the metal
        this bead added over its last width runs off (lost to the 2.5-D map). Returns the mm³ lost."""
        self.end_bead()
        if share <= 0.0 or not self._tail or self.bead == 0:
            return 0.0
        _, ie, je = self._tail[-1]
        r, c = je - self._j0, ie - self._i0
        if self._stamp[r, c] != self.bead:
            return 0.0
        base = float(self._before[r, c])
        rise = float(self._surface_idx(np.array([ie]), np.array([je]))[0]) - base
        u = np.asarray(direction, dtype=float)
        u = u / (float(np.hypot(u[0], u[1])) or 1.0)
        ahead = ((ie + 0.5) * self.cell + u[0] * (width_mm / 2 + 2 * self.cell),
                 (je + 0.5) * self.cell + u[1] * (width_mm / 2 + 2 * self.cell))
        ia, ja = self.index(*ahead)
        self._ensure(ia, ia, ja, ja)
        there = float(self._surface_idx(np.array([ia]), np.array([ja]))[0])
        if rise <= 0.0 or there >= base + 0.5 * rise:
            return 0.0    # the end rests against metal (a closed loop, the next bead): not open
        end = self._path
        last = np.array([(i, j) for s_mm, i, j in self._tail if s_mm >= end - width_mm], dtype=np.int64)
        reach = int(math.ceil(width_mm / 2 / self.cell)) + 1
        i_lo, j_lo = int(last[:, 0].min()) - reach, int(last[:, 1].min()) - reach
        i_hi, j_hi = int(last[:, 0].max()) + reach, int(last[:, 1].max()) + reach
        self._ensure(i_lo, i_hi, j_lo, j_hi)
        gi, gj = np.meshgrid(np.arange(i_lo, i_hi + 1, dtype=np.int64), np.arange(j_lo, j_hi + 1, dtype=np.int64))
        ii, jj = gi.ravel(), gj.ravel()
        d = np.hypot(ii[:, None] - last[None, :, 0], jj[:, None] - last[None, :, 1]).min(axis=1) * self.cell
        rr, cc = jj - self._j0, ii - self._i0
        m = (d <= width_mm / 2 + self.cell) & (self._stamp[rr, cc] == self.bead)
        rr, cc = rr[m], cc[m]
        top = self.top[rr, cc]
        before = self._before[rr, cc]
        ok = np.isfinite(top) & (before > -1e8) & (top > before)   # not off the substrate's edge
        cut = (top[ok] - before[ok]) * share
        self.top[rr[ok], cc[ok]] = top[ok] - cut
        lost = float(np.sum(cut)) * self.cell * self.cell
        self.volume_mm3 -= lost
        return lost

    def _rest_on(self, centre: tuple[int, int]) -> float:
        """The surface at a centre-line cell as it was before this bead: what a pool rests on."""
        cr, cc = centre[1] - self._j0, centre[0] - self._i0
        if self._stamp[cr, cc] == self.bead and self.bead:
            return float(self._before[cr, cc])
        return float(self._surface_idx(np.array([centre[0]]), np.array([centre[1]]))[0])

    def _pour(self, ii: NDArray[np.int64], jj: NDArray[np.int64], env: FloatArray, hang: FloatArray,
              need: float) -> float:
        """Pour `need` (cell-heights) into cells, each held by its parabola `env`; what did not fit.
        Over a free edge (nothing under the cell, nothing laid there yet) the pool hangs on the side
        face down to `hang` (its own height below the bead's base), not lost down the side."""
        r, c = jj - self._j0, ii - self._i0
        old = self._surface_idx(ii, jj)
        floor = np.where(old < _OFF_PART, hang, old)
        level = pour_level(floor, env, need)
        new = np.maximum(floor, np.minimum(level, env))
        fresh = self._stamp[r, c] != self.bead
        self._before[r[fresh], c[fresh]] = old[fresh]
        self._stamp[r, c] = self.bead
        raised = new > floor
        self.top[r[raised], c[raised]] = new[raised]
        return max(need - float(np.sum(new - floor)), 0.0)

    # -- machining -----------------------------------------------------------------------------
    @staticmethod
    def _envelope(a: FloatArray, b: FloatArray, cx: FloatArray, cy: FloatArray, R: float, ball: bool) -> FloatArray:
        """The lowest z of a tool swept from tip a to tip b over each cell centre (inf: out of reach):
        for each cell the tool at 9 places along the path within R of its closest approach (z is
        linear along the move, the tool's profile smooth: the minimum lies there)."""
        d = b - a
        lxy = math.hypot(float(d[0]), float(d[1]))
        if lxy < 1e-9:   # a plunge: the tool at both ends
            s = np.array([[0.0, 1.0]]).repeat(len(cx), axis=0)
        else:
            sc = np.clip(((cx - a[0]) * d[0] + (cy - a[1]) * d[1]) / lxy, 0.0, lxy)
            s = np.clip(sc[:, None] + np.linspace(-R, R, 9)[None, :], 0.0, lxy) / lxy
        px, py, pz = a[0] + s * d[0], a[1] + s * d[1], a[2] + s * d[2]
        d2 = (cx[:, None] - px) ** 2 + (cy[:, None] - py) ** 2
        lift = (R - np.sqrt(np.clip(R * R - d2, 0.0, None))) if ball else np.zeros_like(d2)
        z = np.where(d2 <= R * R, pz + lift, np.inf)
        out: FloatArray = z.min(axis=1)
        return out

    def highest(self) -> float:
        """The highest deposit top (-inf before any)."""
        self.end_bead()
        return float(np.max(self.top, initial=-np.inf, where=~np.isnan(self.top)))

    def carve(self, q0: FloatArray, q1: FloatArray, radius_mm: float, ball: bool) -> tuple[float, float]:
        """Sweep a cutter's tip from q0 to q1 (part frame, tool along +z): every cell's top (deposit
        and substrate alike) comes down to the tool's lower envelope. Returns (volume removed mm³,
        deepest cut mm below the surface it met)."""
        self.end_bead()
        a, b = np.asarray(q0, dtype=float), np.asarray(q1, dtype=float)
        R = float(radius_mm)
        lo, hi = np.minimum(a[:2], b[:2]) - R, np.maximum(a[:2], b[:2]) + R
        i_lo, j_lo = self.index(float(lo[0]), float(lo[1]))
        i_hi, j_hi = self.index(float(hi[0]), float(hi[1]))
        self._ensure(i_lo, i_hi, j_lo, j_hi)
        gi, gj = np.meshgrid(np.arange(i_lo, i_hi + 1, dtype=np.int64), np.arange(j_lo, j_hi + 1, dtype=np.int64))
        ii, jj = gi.ravel(), gj.ravel()
        cx = ((ii + 0.5) * self.cell).astype(np.float64)
        cy = ((jj + 0.5) * self.cell).astype(np.float64)
        env = self._envelope(a, b, cx, cy, R, ball)
        m = np.isfinite(env)
        ii, jj, env = ii[m], jj[m], env[m]
        r, c = jj - self._j0, ii - self._i0
        base = self._base_at(ii, jj)
        surf = np.fmax(self.top[r, c], base)
        below = env < surf - 1e-12
        if not np.any(below):
            return 0.0, 0.0
        r, c, env, surf, base = r[below], c[below], env[below], surf[below], base[below]
        removed = float(np.sum(surf - env) * self.cell * self.cell)
        depth = float(np.max(surf - env))
        top = self.top[r, c]
        self.top[r, c] = np.where(np.isnan(top), np.nan, np.minimum(top, env))
        lower = env < base
        self._base[r[lower], c[lower]] = env[lower]
        self.carved[r[lower], c[lower]] = True
        return removed, depth
