"""The predicted stack: the part's top poured bead by bead as the simulated world pours it
(docs/along-the-path.md "The prediction"; the world's physics: docs/process-physics.md).

A height map of square cells (`cell_mm`) over the plan's xy holds the predicted top of every layer
laid so far (flat at the base before the first). A pass is laid as one continuous bead:

- its width per segment from Ribeiro's forward model at the segment's speed and the synergic
  current of its wire feed (`BeadLaw`), its metal the wire fed (π·D²/4 · WFS / v per mm);
- its footprint: the cells within half a width of its centre line (round ends at its start and
  end, the outside of a turn rounded), each cell to the ~1 mm chunk of the path nearest it;
- the metal fills the lowest cells of a pool first, up to a level, held by Ding's parabola
  (`peak = 1.5·area/w`) resting on the surface at the chunk's centre line as it was before the
  bead: `new = max(old, min(level, base + peak·(1 − (2d/w)²)))`. A bead's first and last bead
  width are one pool each (with the round start and the round end); between them every chunk is
  its own pool.

Levelling inverts that pour: the metal a pool needs to bring its cells to a level T is the volume
between the surface and min(T, parabola), in closed form (`Footprint.need`); only the pour of the
metal a segment can lay (its bounds) needs the level found (`Footprint.pour`, a bisection of all
pools at once).

Pure numpy, deterministic.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["BeadLaw", "Stack", "Footprint", "footprint"]

CHUNK_MM = 1.0       # the pour's unit along the path


@dataclass(frozen=True)
class BeadLaw:
    """Ribeiro's width `w = k1·I^k2·v^k3` and the synergic line (current from wire feed)."""

    k1: float
    k2: float
    k3: float
    i_min: float
    i_max: float
    wfs_min: float
    wfs_max: float

    def current(self, wfs: np.ndarray) -> np.ndarray:
        slope = (self.i_max - self.i_min) / (self.wfs_max - self.wfs_min)
        out: np.ndarray = np.maximum(self.i_min + slope * (wfs - self.wfs_min), 1.0)
        return out

    def width(self, wfs: np.ndarray, speed: np.ndarray) -> np.ndarray:
        out: np.ndarray = self.k1 * self.current(wfs) ** self.k2 * np.maximum(speed, 1e-6) ** self.k3
        return out

    def speed_for(self, width: np.ndarray, wfs: np.ndarray) -> np.ndarray:
        """The travel speed that lays a bead of that width at that wire feed."""
        out: np.ndarray = (width / (self.k1 * self.current(wfs) ** self.k2)) ** (1.0 / self.k3)
        return out


class Stack:
    """The predicted top of the stack (absolute z) on cells of `cell` mm; grows where beads go."""

    MARGIN = 32

    def __init__(self, cell: float, base_z: float) -> None:
        self.cell, self.base_z = cell, base_z
        self.i0 = self.j0 = 0
        self.top = np.full((0, 0), base_z)
        self.memo: dict[bytes, Footprint] = {}   # footprints of passes met before (prisms repeat them)

    def ensure(self, i_lo: int, i_hi: int, j_lo: int, j_hi: int) -> None:
        ny, nx = self.top.shape
        if nx and i_lo >= self.i0 and j_lo >= self.j0 and i_hi < self.i0 + nx and j_hi < self.j0 + ny:
            return
        if nx:
            i_lo, i_hi = min(i_lo, self.i0), max(i_hi, self.i0 + nx - 1)
            j_lo, j_hi = min(j_lo, self.j0), max(j_hi, self.j0 + ny - 1)
        m = self.MARGIN
        new = np.full((j_hi - j_lo + 2 * m + 1, i_hi - i_lo + 2 * m + 1), self.base_z)
        self.memo = {}     # their cells index the old grid
        if nx:
            r, c = self.j0 - j_lo + m, self.i0 - i_lo + m
            new[r:r + ny, c:c + nx] = self.top
        self.top, self.i0, self.j0 = new, i_lo - m, j_lo - m

    def copy(self) -> Stack:
        out = Stack(self.cell, self.base_z)
        out.i0, out.j0, out.top = self.i0, self.j0, self.top.copy()
        out.memo = self.memo
        return out

    def relax(self, carry: float, band_mm: float) -> None:
        """Keep `carry` of every laid cell's departure from the laid cells' median top (the cells
        within `band_mm` of it: a wall's flanks, far below, stay as they are)."""
        laid = self.top > self.base_z + 1e-9
        if carry >= 1.0 or not laid.any():
            return
        level = float(np.median(self.top[laid]))
        near = laid & (np.abs(self.top - level) < band_mm)
        self.top = np.where(near, level + carry * (self.top - level), self.top)

    def take(self, other: Stack) -> None:
        """Become `other` (a copy laid another way)."""
        self.i0, self.j0, self.top = other.i0, other.j0, other.top

    def flat(self, ii: np.ndarray, jj: np.ndarray) -> np.ndarray:
        out: np.ndarray = (jj - self.j0) * self.top.shape[1] + (ii - self.i0)
        return out

    def at(self, xy: np.ndarray) -> np.ndarray:
        """The predicted top at points (inside the grid)."""
        ii = np.floor(xy[:, 0] / self.cell).astype(np.int64)
        jj = np.floor(xy[:, 1] / self.cell).astype(np.int64)
        out: np.ndarray = self.top.ravel()[self.flat(ii, jj)]
        return out


@dataclass(frozen=True)
class Footprint:
    """One pass's cells on a stack's grid, the chunk and segment each belongs to, the pools (the
    geometry alone: the same for every stack of that grid, `Stack.copy` included).

    A cell under two pools of the bead (inside a turn, a ring closing over its start) is poured by
    both, the later one on what the earlier one left, as the world pours a bead in order: the pools
    are poured in waves (`wave`), a pool after every earlier pool it shares a cell with."""

    cells: np.ndarray      # (K,) flat cell index
    seg: np.ndarray        # (K,) segment of each cell
    chunk: np.ndarray      # (K,) chunk of each cell
    d: np.ndarray          # (K,) distance to the centre line
    wave: np.ndarray       # (K,) the wave the cell's pool is poured in (after the pools whose cells it meets)
    pool: np.ndarray       # (C,) pool of each chunk
    chunk_seg: np.ndarray  # (C,) segment of each chunk
    chunk_len: np.ndarray  # (C,) mm of path of each chunk
    chunk_metal: np.ndarray  # (C,) mm of path each chunk's metal stands for (its strip's cells)
    centre: np.ndarray     # (C,) flat cell of each chunk's middle
    n_pool: int
    cell: float

    def _env(self, stack: Stack, area: np.ndarray, width: np.ndarray) -> np.ndarray:
        """Each cell's parabola top (-inf outside its segment's width), on the stack before the bead."""
        w = width[self.seg]
        env = stack.top.ravel()[self.centre][self.chunk] + 1.5 * area[self.seg] / w * (1.0 - (2.0 * self.d / w) ** 2)
        out: np.ndarray = np.where(self.d <= w / 2.0, env, -np.inf)
        return out

    def path_of(self, n_seg: int) -> np.ndarray:
        """mm of path each segment's metal stands for (its strip's cells)."""
        out: np.ndarray = np.bincount(self.chunk_seg, weights=self.chunk_metal, minlength=n_seg)
        return out

    def need(self, stack: Stack, level: np.ndarray, area: np.ndarray, width: np.ndarray) -> np.ndarray:
        """mm³ of metal each segment needs for its pools to stand at `level` (per chunk; a pool's
        need shared by its chunks as their metal); the late pools on the others standing there."""
        env = self._env(stack, area, width)
        flat = stack.top.ravel()
        at = level[self.chunk]
        fill = np.clip(np.minimum(at, env) - flat[self.cells], 0.0, None)
        if len(self.wave) and self.wave[-1] > 0:
            surf = flat.copy()
            for part in self._waves():
                fill[part] = np.clip(np.minimum(at[part], env[part]) - surf[self.cells[part]], 0.0, None)
                surf[self.cells[part]] += fill[part]
        per_pool = np.bincount(self.pool[self.chunk], weights=fill, minlength=self.n_pool) * self.cell ** 2
        pool_metal = np.bincount(self.pool, weights=self.chunk_metal, minlength=self.n_pool)
        per_chunk = per_pool[self.pool] * self.chunk_metal / np.maximum(pool_metal[self.pool], 1e-12)
        out: np.ndarray = np.bincount(self.chunk_seg, weights=per_chunk, minlength=len(area))
        return out

    def reach(self, stack: Stack, level: np.ndarray, width: np.ndarray) -> np.ndarray:
        """mm² per mm each segment needs for its parabola's peak to reach `level` over every chunk's
        centre (a pool over a dip: the metal a level fill needs may not lift a parabola that high)."""
        base = stack.top.ravel()[self.centre]
        out = np.zeros(len(width))
        np.maximum.at(out, self.chunk_seg, (level - base) * width[self.chunk_seg] / 1.5)
        return out

    def pour(self, stack: Stack, area: np.ndarray, width: np.ndarray, guess: float | None = None) -> np.ndarray:
        """The stack's top (flat) after the pass lays `area` mm² per mm on each segment. What does
        not fit in a pool runs on into the bead's next pools, as in the world (sims/heightmap.py:
        the inside of a turn, where the pools overlap, fills the outside of it)."""
        env = self._env(stack, area, width)
        metal = np.bincount(self.pool, weights=area[self.chunk_seg] * self.chunk_metal,
                            minlength=self.n_pool) / self.cell ** 2
        surf, room = self._poured(stack, env, metal, guess)
        for _ in range(SPILL_ROUNDS):   # the rooms change as the spill lands: a few rounds
            carried = _spilled(metal, room)
            if carried is None:
                break
            surf, room = self._poured(stack, env, carried, guess)
        return surf

    def _poured(self, stack: Stack, env: np.ndarray, metal: np.ndarray, guess: float | None
                ) -> tuple[np.ndarray, np.ndarray]:
        """The stack's top after each pool poured its `metal`, wave after wave; each pool's room."""
        surf = stack.top.ravel().copy()
        p = self.pool[self.chunk]
        room = np.zeros(self.n_pool)
        for part in self._waves():
            cells = self.cells[part]
            old = surf[cells]
            room += np.bincount(p[part], weights=np.clip(env[part] - old, 0.0, None), minlength=self.n_pool)
            np.maximum.at(surf, cells, _fill(p[part], old, env[part], metal, self.n_pool, guess))
        return surf, room

    def _waves(self) -> list[slice]:
        """The cells of each wave of pools, in pouring order (the cells are sorted by wave)."""
        if not len(self.wave):
            return []
        cut = np.flatnonzero(np.diff(self.wave)) + 1
        return [slice(int(a), int(b)) for a, b in zip(np.r_[0, cut], np.r_[cut, len(self.wave)])]

    def commit(self, stack: Stack, surf: np.ndarray) -> None:
        """Make a pour the stack's top."""
        stack.top = surf.reshape(stack.top.shape)

    def tops(self, stack: Stack) -> np.ndarray:
        """The stack's top at every chunk's centre."""
        out: np.ndarray = stack.top.ravel()[self.centre]
        return out


def _spilled(metal: np.ndarray, room: np.ndarray) -> np.ndarray | None:
    """Each pool's metal with what the pools before it could not hold run on into it (in the
    bead's order; what the last cannot hold is lost); None when every pool holds its own."""
    over = metal > room + 1e-9
    if not over[:-1].any():
        return None
    out = metal.copy()
    carry = 0.0
    for k, (m, r) in enumerate(zip(metal.tolist(), room.tolist())):
        have = m + carry
        out[k], carry = min(have, r), max(have - r, 0.0)
    return out


def _fill(p: np.ndarray, old: np.ndarray, env: np.ndarray, need: np.ndarray, n_pool: int,
          guess: float | None) -> np.ndarray:
    """Every pool's metal (`need`, cell-heights) into its cells (`p` the pool of each): the lowest
    first up to a level, each cell held by its parabola `env`; the level by Newton's method on the
    filled volume, kept inside a bracket (all pools at once). A pool with more than its room is
    full (the rest spills, as in the world)."""
    room = env > old
    lo = np.full(n_pool, np.inf)
    np.minimum.at(lo, p[room], old[room])
    hi = np.full(n_pool, -np.inf)
    np.maximum.at(hi, p[room], env[room])
    full = np.bincount(p, weights=np.where(room, env - old, 0.0), minlength=n_pool)
    some = np.isfinite(lo)
    lo, hi = np.where(some, lo, 0.0), np.where(some, hi, 0.0)
    c = 0.5 * (lo + hi) if guess is None else np.clip(np.full(n_pool, guess), lo, hi)
    for _ in range(NEWTON):
        got = np.bincount(p, weights=np.clip(np.minimum(c[p], env) - old, 0.0, None), minlength=n_pool)
        short = need - got
        if float(np.max(np.abs(np.where(need < full, short, 0.0)), initial=0.0)) < 1e-6 * max(float(need.max(initial=0.0)), 1.0):
            break
        wet = np.bincount(p, weights=((old < c[p]) & (c[p] < env)).astype(float), minlength=n_pool)
        low = short > 0
        lo, hi = np.where(low, c, lo), np.where(low, hi, c)
        step = c + short / np.maximum(wet, 1e-9)
        c = np.where((wet > 0) & (step > lo) & (step < hi), step, 0.5 * (lo + hi))
    level = np.where(need >= full, np.inf, c)
    out: np.ndarray = np.maximum(old, np.minimum(level[p], env))
    return out


NEWTON = 12   # iterations of a pour's level (Newton's, bisection where it leaves the bracket)


MEMO = 64   # footprints a stack keeps
SPILL_ROUNDS = 2   # pours of a pass with its spill run on (the pools' rooms taken from the pour before)


def footprint(stack: Stack, pts: np.ndarray, width: np.ndarray, pool_mm: float) -> Footprint:
    """A pass's footprint on the stack's grid (grown to hold it): `pts` (N + 1, 2) its centre line,
    `width` (N,) the widest each segment may be laid (cells are taken out to half of it; the pour
    masks each segment's own). A pass met before on the same grid: its footprint again."""
    r = width / 2.0
    lo = np.floor((np.minimum(pts[:-1], pts[1:]) - r[:, None]) / stack.cell).astype(np.int64)
    hi = np.floor((np.maximum(pts[:-1], pts[1:]) + r[:, None]) / stack.cell).astype(np.int64)
    stack.ensure(int(lo[:, 0].min()), int(hi[:, 0].max()), int(lo[:, 1].min()), int(hi[:, 1].max()))
    key = np.ascontiguousarray(pts).tobytes() + np.ascontiguousarray(width).tobytes() + np.float64(pool_mm).tobytes()
    hit = stack.memo.get(key)
    if hit is None:
        if len(stack.memo) >= MEMO:
            stack.memo.clear()
        hit = stack.memo[key] = _footprint(stack, pts, width, pool_mm, lo, hi)
    return hit


def _footprint(stack: Stack, pts: np.ndarray, width: np.ndarray, pool_mm: float, lo: np.ndarray,
               hi: np.ndarray) -> Footprint:
    cell = stack.cell
    a, b = pts[:-1], pts[1:]
    dv = b - a
    L = np.hypot(dv[:, 0], dv[:, 1])
    u = dv / np.maximum(L, 1e-12)[:, None]
    r = width / 2.0
    nx, ny = hi[:, 0] - lo[:, 0] + 1, hi[:, 1] - lo[:, 1] + 1
    cnt = np.where(L > 1e-9, nx * ny, 0)
    seg = np.repeat(np.arange(len(L), dtype=np.int32), cnt)
    k = np.arange(int(cnt.sum()), dtype=np.int32) - np.repeat((np.cumsum(cnt) - cnt).astype(np.int32), cnt)
    row, col = np.divmod(k, nx.astype(np.int32)[seg])
    # each segment's frame: its start's offset from its box's corner cell centre, folded in
    ox = (lo[:, 0] + 0.5) * cell - a[:, 0]
    oy = (lo[:, 1] + 0.5) * cell - a[:, 1]
    cx, cy = col * cell + ox[seg], row * cell + oy[seg]
    ux, uy = u[seg, 0], u[seg, 1]
    t = cx * ux + cy * uy
    s = cy * ux - cx * uy
    Ls = L[seg]
    over = np.maximum(t - Ls, 0.0) + np.maximum(-t, 0.0)
    d = np.sqrt(over * over + s * s)
    keep = d <= r[seg]
    # a bead goes on across its joints: no round start but the first, a round end only outside a turn
    nz = np.flatnonzero(L > 1e-9)
    prev = np.zeros(len(L), dtype=bool)
    prev[nz[1:]] = True
    nxt = np.full(len(L), -1)
    nxt[nz[:-1]] = nz[1:]
    keep &= ~((t < 0.0) & prev[seg])
    # (a cell right on a joint, a grid row through it, is the next segment's: counted once)
    beyond = keep & (t > Ls - 1e-9) & (nxt[seg] >= 0)
    if beyond.any():
        bi = np.flatnonzero(beyond)
        un = u[nxt[seg[bi]]]
        tn = (cx[bi] - Ls[bi] * ux[bi]) * un[:, 0] + (cy[bi] - Ls[bi] * uy[bi]) * un[:, 1]
        keep[bi[tn >= 0.0]] = False
    idx = np.flatnonzero(keep)
    seg, d, t = seg[idx], d[idx], t[idx]
    tc = np.clip(t, 0.0, L[seg])
    beside = (t >= 0.0) & (t <= L[seg])
    cells = (lo[seg, 1] - stack.j0 + row[idx]) * stack.top.shape[1] + (lo[seg, 0] - stack.i0 + col[idx])
    # the chunks: each segment cut into ~1 mm pieces
    n = np.where(L > 1e-9, np.maximum(1, np.ceil(L / CHUNK_MM - 1e-9)), 0).astype(np.int64)
    c0 = np.cumsum(n) - n
    step = L / np.maximum(n, 1)
    chunk = c0[seg] + np.minimum((tc / np.maximum(step[seg], 1e-12)).astype(np.int64), np.maximum(n[seg] - 1, 0))
    chunk_seg = np.repeat(np.arange(len(L)), n)
    kk = np.arange(int(n.sum())) - c0[chunk_seg]
    chunk_len = step[chunk_seg]
    path0 = np.r_[0.0, np.cumsum(L)][:-1]
    s_mid = path0[chunk_seg] + (kk + 0.5) * chunk_len
    mid = a[chunk_seg] + u[chunk_seg] * ((kk + 0.5) * chunk_len)[:, None]
    centre = stack.flat(np.floor(mid[:, 0] / cell).astype(np.int64), np.floor(mid[:, 1] / cell).astype(np.int64))
    pool, n_pool = _pools(s_mid, float(L.sum()), pool_mm)
    # a cell in two segments' strips of one pool: once, to the nearer; of two pools: in both, the
    # later pool poured after the others (inside a turn, a ring closing over its start)
    entry_pool = pool[chunk]
    order = np.lexsort((d, cells, entry_pool))
    ep, ec = entry_pool[order], cells[order]
    first = np.r_[True, (ep[1:] != ep[:-1]) | (ec[1:] != ec[:-1])]
    sel = np.sort(order[first])
    seg, cells, tc, d, beside, chunk = seg[sel], cells[sel], tc[sel], d[sel], beside[sel], chunk[sel]
    wave = _waves(cells, pool[chunk], n_pool)[pool[chunk]]
    # each cell beside the path holds the same metal (a chunk covering one row of cells or two
    # lays in proportion): the pass's path over its strip's cells
    strip = np.bincount(chunk[beside], minlength=len(chunk_seg)).astype(float)
    chunk_metal = strip * float(L.sum()) / max(float(strip.sum()), 1.0)
    by = np.argsort(wave, kind="stable")     # the cells in pouring order: a wave a slice
    return Footprint(cells[by], seg[by], chunk[by], d[by], wave[by], pool, chunk_seg, chunk_len, chunk_metal, centre,
                     n_pool, cell)


def _waves(cells: np.ndarray, cell_pool: np.ndarray, n_pool: int) -> np.ndarray:
    """Each pool's wave: 0, or one more than the latest wave of the earlier pools it shares a cell
    with (the pools of a wave share no cell: poured together, each on what the waves before left)."""
    wave = np.zeros(n_pool, dtype=np.int64)
    order = np.lexsort((cell_pool, cells))
    c, p = cells[order], cell_pool[order]
    same = c[1:] == c[:-1]
    pairs = np.unique(np.column_stack([p[:-1][same], p[1:][same]]), axis=0)
    for a, b in pairs[np.argsort(pairs[:, 1], kind="stable")].tolist():
        wave[b] = max(wave[b], wave[a] + 1)
    return wave


def _pools(s_mid: np.ndarray, total: float, pool_mm: float) -> tuple[np.ndarray, int]:
    """The pool of each chunk: the first `pool_mm` one, the last `pool_mm` one, each between alone."""
    if total <= pool_mm:
        return np.zeros(len(s_mid), dtype=np.int64), 1
    start = s_mid < pool_mm
    end = (s_mid >= max(total - pool_mm, pool_mm)) & ~start
    middle = ~start & ~end
    pool = np.zeros(len(s_mid), dtype=np.int64)
    pool[middle] = 1 + np.arange(int(middle.sum()))
    pool[end] = 1 + int(middle.sum())
    return pool, 2 + int(middle.sum())
