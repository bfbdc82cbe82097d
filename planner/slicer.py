"""Slice every layer at once from the triangle arrays into closed contours with facet normals.

Each (face, plane) crossing gives one segment, oriented so the material lies on its left (outer
contours counter-clockwise). Segments are chained exactly through the mesh edge they end on (no
float matching); what stays open is joined end-to-start with growing tolerances and, if still
open, reported.
"""
from __future__ import annotations

from typing import Any

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class Contour:
    points: np.ndarray  # (n, 2) mm, closing point not repeated
    normals: np.ndarray  # (n, 3) facet normal of the face each point's segment came from
    closed: bool
    gap_mm: float = 0.0  # largest gap bridged to close it (0 when closed exactly)


@dataclass(frozen=True)
class LayerSlice:
    index: int
    z_mm: float  # the cutting plane
    contours: tuple[Contour, ...] = field(default_factory=tuple)

    @property
    def open_contours(self) -> tuple[Contour, ...]:
        return tuple(c for c in self.contours if not c.closed)


def slice_levels(height_mm: float, layer_mm: float) -> np.ndarray:
    """Cutting planes at mid-layer: (i + 0.5)·h for every layer whose middle is inside the part."""
    n = int(np.floor(height_mm / layer_mm + 0.5))
    return (np.arange(max(n, 1)) + 0.5) * layer_mm


def face_z_range(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each face's lowest and highest z, corner by corner (no (F, 3) array reduced along its rows)."""
    zc = np.ascontiguousarray(vertices[:, 2])
    f = np.asarray(faces)
    z0, z1, z2 = np.take(zc, f[:, 0]), np.take(zc, f[:, 1]), np.take(zc, f[:, 2])
    return np.minimum(np.minimum(z0, z1), z2), np.maximum(np.maximum(z0, z1), z2)


def slice_mesh(vertices: np.ndarray, faces: np.ndarray, face_normals: np.ndarray, levels: np.ndarray,
               gap_tolerances: tuple[float, ...] = (1e-6, 0.05, 0.5, 2.0),
               z_range: tuple[np.ndarray, np.ndarray] | None = None) -> list[LayerSlice]:
    """All layers at once. `gap_tolerances` (mm) are tried in order to close open chains;
    `z_range`: face_z_range(vertices, faces) when the caller has it."""
    levels = np.asarray(levels, dtype=np.float64)
    zmin, zmax = z_range if z_range is not None else face_z_range(vertices, faces)
    seg_layer, seg_a, seg_b, seg_face, key_start, key_end = _segments(vertices, faces, levels, zmin, zmax)
    slices = []
    order = np.argsort(seg_layer, kind="stable")
    bounds = np.searchsorted(seg_layer[order], np.arange(len(levels) + 1))
    for li in range(len(levels)):
        idx = order[bounds[li]:bounds[li + 1]]
        contours = _assemble(seg_a[idx], seg_b[idx], face_normals[seg_face[idx]],
                             key_start[idx], key_end[idx], gap_tolerances)
        slices.append(LayerSlice(li, float(levels[li]), tuple(contours)))
    return slices


def _segments(vertices: np.ndarray, faces: np.ndarray, levels: np.ndarray, zmin: np.ndarray, zmax: np.ndarray) -> Any:
    # A vertex on a plane counts as above it, so every crossing face has exactly one "up" edge.
    lo = np.searchsorted(levels, zmin, side="right")
    hi = np.searchsorted(levels, zmax, side="right")
    count = np.maximum(hi - lo, 0)
    crossing = np.flatnonzero(count)  # the few faces a plane cuts: the per-segment work is theirs alone
    count = count[crossing]
    total = int(count.sum())
    face = np.repeat(crossing, count)
    offs = np.repeat(np.cumsum(count) - count, count)
    layer = lo[face] + (np.arange(total) - offs)
    z = levels[layer]
    fz = vertices[:, 2][faces[face]]
    above = fz >= z[:, None]
    nxt = np.array([1, 2, 0])
    up = ~above & above[:, nxt]  # edge j goes from below to above
    down = above & ~above[:, nxt]
    ju = np.argmax(up, axis=1)
    jd = np.argmax(down, axis=1)
    fv = faces[face]
    rows = np.arange(total)

    def cut(j: int) -> Any:
        ia, ib = fv[rows, j], fv[rows, nxt[j]]
        a, b = vertices[ia], vertices[ib]
        t = (z - a[:, 2]) / (b[:, 2] - a[:, 2])
        p = a[:, :2] + t[:, None] * (b[:, :2] - a[:, :2])
        lo_v, hi_v = np.minimum(ia, ib), np.maximum(ia, ib)
        nv = np.int64(len(vertices))
        key = (layer.astype(np.int64) * nv + lo_v) * nv + hi_v
        return p, key

    # Material on the left: the segment runs from the "down" edge to the "up" edge.
    pa, ka = cut(jd)
    pb, kb = cut(ju)
    return layer, pa, pb, face, ka, kb


def _assemble(pa: np.ndarray, pb: np.ndarray, normals: np.ndarray, ks: np.ndarray, ke: np.ndarray,
              tolerances: tuple[float, ...]) -> list[Contour]:
    n = len(pa)
    if n == 0:
        return []
    order = np.argsort(ks, kind="stable")
    sk = ks[order]
    pos = np.searchsorted(sk, ke)
    pos_c = np.minimum(pos, n - 1)
    hit = (pos < n) & (sk[pos_c] == ke)
    nxt = np.where(hit, order[pos_c], -1)
    # Non-manifold edges can make two segments point at the same successor: keep the first.
    succ_taken = np.zeros(n, dtype=bool)
    nxt_list = nxt.tolist()
    has_pred = [False] * n
    for i, j in enumerate(nxt_list):
        if j >= 0:
            if succ_taken[j]:
                nxt_list[i] = -1
            else:
                succ_taken[j] = True
                has_pred[j] = True
    visited = [False] * n
    chains: list[list[int]] = []
    closed_flags: list[bool] = []
    # Open chains first (they start where no segment leads in), then the cycles.
    for start in [i for i in range(n) if not has_pred[i]] + list(range(n)):
        if visited[start]:
            continue
        chain = []
        i = start
        while i >= 0 and not visited[i]:
            visited[i] = True
            chain.append(i)
            i = nxt_list[i]
        chains.append(chain)
        closed_flags.append(i == start)
    contours = [_contour(pa, pb, normals, c, closed, 0.0) for c, closed in zip(chains, closed_flags) if closed]
    open_chains = [c for c, closed in zip(chains, closed_flags) if not closed]
    if open_chains:
        contours += _close_gaps(pa, pb, normals, open_chains, tolerances)
    return [c for c in contours if len(c.points) >= 3 or not c.closed]


def _contour(pa: np.ndarray, pb: np.ndarray, normals: np.ndarray, idx: Any, closed: bool, gap: float) -> Contour:
    idx = np.asarray(idx)
    pts = pa[idx]
    nrm = normals[idx]
    if not closed:
        pts = np.vstack([pts, pb[idx[-1]]])
        nrm = np.vstack([nrm, normals[idx[-1]]])
    # Drop zero-length steps (a vertex on the plane gives coincident cut points).
    step = np.linalg.norm(np.diff(pts, axis=0, append=pts[:1]), axis=1) if closed else \
        np.r_[np.linalg.norm(np.diff(pts, axis=0), axis=1), 1.0]
    keep = step > 1e-9
    if not keep.any():
        keep[0] = True
    return Contour(pts[keep], nrm[keep], closed, gap)


def _close_gaps(pa: np.ndarray, pb: np.ndarray, normals: np.ndarray, chains: list[Any],
                tolerances: tuple[float, ...]) -> list[Contour]:
    """Join open chains end-to-start (or a chain to itself) with growing tolerances."""
    pieces = [list(c) for c in chains]
    gaps = [0.0] * len(pieces)
    closed = [False] * len(pieces)
    alive = [True] * len(pieces)
    for tol in tolerances:
        changed = True
        while changed:
            changed = False
            live = [i for i in range(len(pieces)) if alive[i] and not closed[i]]
            if not live:
                break
            ends = np.array([pb[pieces[i][-1]] for i in live])
            starts = np.array([pa[pieces[i][0]] for i in live])
            d = np.linalg.norm(ends[:, None, :] - starts[None, :, :], axis=2)
            flat = int(np.argmin(d))
            a, b = divmod(flat, len(live))
            if d[a, b] > tol:
                continue
            ia, ib = live[a], live[b]
            if ia == ib:
                closed[ia] = True
                gaps[ia] = max(gaps[ia], float(d[a, b]))
            else:
                pieces[ia] = pieces[ia] + pieces[ib]
                gaps[ia] = max(gaps[ia], gaps[ib], float(d[a, b]))
                alive[ib] = False
            changed = True
    return [_contour(pa, pb, normals, pieces[i], closed[i], gaps[i]) for i in range(len(pieces)) if alive[i]]
