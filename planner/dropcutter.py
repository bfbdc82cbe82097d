"""Drop-cutter: where a cutter coming down along -Z first touches a surface (pure numpy).

A cutter is a `ToolShape`: a flat end mill (a disk of radius R at its tip) or a ball end mill (a
sphere of radius R whose lowest point is the tip). For a cutter location (x, y) the drop-cutter
gives the lowest tip z at which the tool touches the surface and nowhere goes into it:

- `drop_mesh`: exact against a triangle mesh, the tests of every triangle's vertices, facet and
  edges (the algorithm opencamlib implements): the tool's tip z is the highest of them;
- `drop_map`: against a height map (a grid of tops, NaN: nothing there), the grey dilation of
  the map by the tool's profile, exact at the grid's points.

`scallop_height` and `stepover_for_scallop` are the ball's cusp between neighbouring passes on a
flat surface, h = R - sqrt(R² - (s/2)²) (docs/machining.md).
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray

F = NDArray[np.float64]
_EPS = 1e-12


@dataclass(frozen=True)
class ToolShape:
    kind: Literal["flat", "ball"]
    radius_mm: float

    def profile(self, r: F) -> F:
        """Height of the cutting surface above the tip at radial distance r (inf beyond R)."""
        R = self.radius_mm
        r = np.asarray(r, dtype=float)
        inside = r <= R + 1e-12
        if self.kind == "flat":
            return np.where(inside, 0.0, np.inf)
        return np.where(inside, R - np.sqrt(np.clip(R * R - r * r, 0.0, None)), np.inf)


def scallop_height(tool: ToolShape, stepover_mm: float) -> float:
    """The cusp a tool leaves between two passes `stepover_mm` apart on a flat surface."""
    if tool.kind == "flat":
        return 0.0 if stepover_mm <= 2 * tool.radius_mm else math.inf
    R, half = tool.radius_mm, stepover_mm / 2.0
    return R - math.sqrt(max(R * R - half * half, 0.0)) if half <= R else math.inf


def stepover_for_scallop(tool: ToolShape, scallop_mm: float, max_stepover_mm: float) -> float:
    """The widest stepover (≤ max_stepover_mm) whose scallop is at most `scallop_mm`."""
    if tool.kind == "flat":
        return min(max_stepover_mm, 1.6 * tool.radius_mm)
    R = tool.radius_mm
    h = min(scallop_mm, R)
    return min(max_stepover_mm, 2.0 * math.sqrt(max(R * R - (R - h) ** 2, 0.0)))


# -- against a triangle mesh ------------------------------------------------------------------

def _vertex(tool: ToolShape, px: F, py: F, v: F) -> F:
    """(P, T) tip z from touching the vertices v (T, 3)."""
    dx = px[:, None] - v[None, :, 0]
    dy = py[:, None] - v[None, :, 1]
    d2 = dx * dx + dy * dy
    R2 = tool.radius_mm ** 2
    ok = d2 <= R2
    if tool.kind == "flat":
        z = np.broadcast_to(v[None, :, 2], d2.shape)
    else:
        z = v[None, :, 2] + np.sqrt(np.clip(R2 - d2, 0.0, None)) - tool.radius_mm
    return np.where(ok, z, -np.inf)


def _inside(qx: F, qy: F, a: F, b: F, c: F) -> NDArray[np.bool_]:
    """Is (qx, qy) (P, T) inside the xy projection of triangles (a, b, c) (T, 3)?"""
    def cross(p: F, q: F, x: F, y: F) -> F:
        return (q[None, :, 0] - p[None, :, 0]) * (y - p[None, :, 1]) - (q[None, :, 1] - p[None, :, 1]) * (x - p[None, :, 0])
    d1, d2, d3 = cross(a, b, qx, qy), cross(b, c, qx, qy), cross(c, a, qx, qy)
    tol = 1e-9
    neg = (d1 < -tol) | (d2 < -tol) | (d3 < -tol)
    pos = (d1 > tol) | (d2 > tol) | (d3 > tol)
    return ~(neg & pos)


def _facet(tool: ToolShape, px: F, py: F, tri: F) -> F:
    """(P, T) tip z from touching the facets' interiors."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    n = np.cross(b - a, c - a)
    ln = np.linalg.norm(n, axis=1)
    n = n / np.where(ln > _EPS, ln, 1.0)[:, None]
    n = np.where((n[:, 2] < 0)[:, None], -n, n)
    nz = n[:, 2]
    good = nz > 1e-9
    nzs = np.where(good, nz, 1.0)
    R = tool.radius_mm
    if tool.kind == "ball":
        qx = px[:, None] - R * n[None, :, 0]
        qy = py[:, None] - R * n[None, :, 1]
    else:
        nxy = np.hypot(n[:, 0], n[:, 1])
        ux = np.where(nxy > 1e-12, -n[:, 0] / np.where(nxy > 1e-12, nxy, 1.0), 0.0)
        uy = np.where(nxy > 1e-12, -n[:, 1] / np.where(nxy > 1e-12, nxy, 1.0), 0.0)
        qx = px[:, None] + R * ux[None, :]
        qy = py[:, None] + R * uy[None, :]
    # the plane's z at the contact point's xy
    zc = a[None, :, 2] - (n[None, :, 0] * (qx - a[None, :, 0]) + n[None, :, 1] * (qy - a[None, :, 1])) / nzs[None, :]
    ok = good[None, :] & _inside(qx, qy, a, b, c)
    if tool.kind == "ball":
        zc = zc + R * nz[None, :] - R   # centre = contact + R n; tip = centre - R
    return np.where(ok, zc, -np.inf)


def _edge(tool: ToolShape, px: F, py: F, p0: F, p1: F) -> F:
    """(P, T) tip z from touching the edges p0→p1 (T, 3) between their ends."""
    u = p1 - p0
    ux, uy, uz = u[None, :, 0], u[None, :, 1], u[None, :, 2]
    wx = px[:, None] - p0[None, :, 0]
    wy = py[:, None] - p0[None, :, 1]
    A = ux * ux + uy * uy
    good = A > 1e-12
    As = np.where(good, A, 1.0)
    R = tool.radius_mm
    if tool.kind == "ball":
        uu = A + uz * uz
        B = -2.0 * uz * (wx * ux + wy * uy)
        C = uz * uz * (wx * wx + wy * wy) + (wx * uy - wy * ux) ** 2 - R * R * uu
        disc = B * B - 4.0 * A * C
        ok = good & (disc >= 0)
        t = (-B + np.sqrt(np.clip(disc, 0.0, None))) / (2.0 * As)
        s = (wx * ux + wy * uy + t * uz) / np.where(uu > _EPS, uu, 1.0)
        ok &= (s >= 0.0) & (s <= 1.0)
        return np.where(ok, p0[None, :, 2] + t - R, -np.inf)
    # flat: the part of the edge within R in xy; z is linear along it, highest at an end
    bq = -2.0 * (wx * ux + wy * uy)
    cq = wx * wx + wy * wy - R * R
    disc = bq * bq - 4.0 * A * cq
    ok = good & (disc >= 0)
    sq = np.sqrt(np.clip(disc, 0.0, None))
    s1u = (-bq - sq) / (2.0 * As)
    s2u = (-bq + sq) / (2.0 * As)
    ok &= (s1u <= 1.0) & (s2u >= 0.0)   # the chord inside the disk overlaps the edge
    s1, s2 = np.clip(s1u, 0.0, 1.0), np.clip(s2u, 0.0, 1.0)
    z = p0[None, :, 2] + np.maximum(s1 * uz, s2 * uz)
    return np.where(ok, z, -np.inf)


def _drop_block(tool: ToolShape, px: F, py: F, tri: F) -> F:
    z: F = np.full(len(px), -np.inf)
    if len(tri) == 0:
        return z
    z = np.maximum(z, _facet(tool, px, py, tri).max(axis=1))
    # a triangle wholly below every point's facet contact cannot raise any of them: no vertex or
    # edge test for it (the tip never rises above a triangle's highest vertex)
    keep = tri[:, :, 2].max(axis=1) > z.min()
    t = tri[keep]
    for k in range(3 if len(t) else 0):
        z = np.maximum(z, _vertex(tool, px, py, t[:, k]).max(axis=1))
        z = np.maximum(z, _edge(tool, px, py, t[:, k], t[:, (k + 1) % 3]).max(axis=1))
    return z


def drop_mesh(tool: ToolShape, triangles: F, xy: F, bucket_mm: float | None = None) -> F:
    """Tip z of `tool` dropped onto the mesh `triangles` (n, 3, 3) at each cutter location xy (m, 2);
    -inf where no triangle lies under the tool. Exact (vertex, facet and edge contacts)."""
    tri = np.asarray(triangles, dtype=float).reshape(-1, 3, 3)
    pts = np.asarray(xy, dtype=float).reshape(-1, 2)
    out = np.full(len(pts), -np.inf)
    if len(pts) == 0 or len(tri) == 0:
        return out
    R = tool.radius_mm
    lo = pts.min(axis=0)
    span = np.maximum(pts.max(axis=0) - lo, 1e-6)
    # buckets of about 2000 points (the triangles near each are looked up once per bucket)
    size = bucket_mm or max(float(np.sqrt(span[0] * span[1] * 2000.0 / len(pts))), 4.0 * R, 1.0)
    key = np.floor((pts - lo) / size).astype(np.int64)
    tlo = tri[:, :, :2].min(axis=1) - R
    thi = tri[:, :, :2].max(axis=1) + R
    order = np.lexsort((key[:, 1], key[:, 0]))
    ks = key[order]
    cuts = np.flatnonzero(np.any(np.diff(ks, axis=0) != 0, axis=1)) + 1
    for grp in np.split(order, cuts):
        g = pts[grp]
        blo, bhi = g.min(axis=0), g.max(axis=0)
        sel = np.all(thi >= blo, axis=1) & np.all(tlo <= bhi, axis=1)
        cand = tri[sel]
        for c0 in range(0, len(grp), 4096):
            part = grp[c0:c0 + 4096]
            out[part] = _drop_block(tool, pts[part, 0], pts[part, 1], cand)
    return out


# -- against a height map ---------------------------------------------------------------------

def drop_map(tool: ToolShape, heights: F, origin: tuple[float, float], cell_mm: float) -> F:
    """Tip z of `tool` dropped at every grid point of a height map (`heights[j, i]` at x = origin
    x + i·cell, y = origin y + j·cell; NaN: nothing there): the map dilated by the tool's profile.
    -inf where nothing lies under the tool."""
    h = np.where(np.isfinite(heights), heights, -np.inf)
    R = tool.radius_mm
    k = int(math.floor(R / cell_mm + 1e-9))
    ny, nx = h.shape
    pad = np.full((ny + 2 * k, nx + 2 * k), -np.inf)
    pad[k:k + ny, k:k + nx] = h
    out = np.full_like(h, -np.inf)
    for dj in range(-k, k + 1):
        for di in range(-k, k + 1):
            r = math.hypot(di, dj) * cell_mm
            if r > R + 1e-9:
                continue
            lift = float(tool.profile(np.array(r)))
            np.maximum(out, pad[k + dj:k + dj + ny, k + di:k + di + nx] - lift, out=out)
    return out
