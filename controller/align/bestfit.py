"""Full rigid best fit: Kabsch for paired points, ICP of probed points against the CAD mesh.

Rigid only: no scale, no reflection. Pure: arrays (and a trimesh mesh) in, frozen dataclasses out.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from controller.motion.kinematics import rotation_matrix
from core.errors import InputError

if TYPE_CHECKING:  # trimesh loads on first use (start-up time)
    import trimesh

F = NDArray[np.float64]


@dataclass(frozen=True)
class RigidFit:
    rotation: F                  # 3×3, det +1
    translation: F               # 3
    rms_mm: float                # RMS distance after the fit
    max_residual_mm: float
    iterations: int = 1
    converged: bool = True

    @property
    def matrix(self) -> F:
        m = np.eye(4)
        m[:3, :3] = self.rotation
        m[:3, 3] = self.translation
        return m


def _pts(a: ArrayLike, what: str) -> F:
    p = np.asarray(a, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or not np.all(np.isfinite(p)):
        raise InputError(f"{what}: expected finite (n, 3) points, got shape {p.shape}")
    return p


def kabsch(src: ArrayLike, dst: ArrayLike, weights: ArrayLike | None = None) -> RigidFit:
    """Rotation R and translation t minimising Σ w|R·src + t − dst|² (no scale, no reflection)."""
    s, d = _pts(src, "kabsch source"), _pts(dst, "kabsch target")
    if s.shape != d.shape:
        raise InputError(f"kabsch: {len(s)} source points but {len(d)} targets; pair them one to one")
    if len(s) < 3:
        raise InputError("kabsch: needs at least 3 point pairs")
    w = np.ones(len(s)) if weights is None else np.asarray(weights, dtype=float)
    w = w / w.sum()
    cs, cd = w @ s, w @ d
    h = (s - cs).T @ ((d - cd) * w[:, None])
    u, sv, vt = np.linalg.svd(h)
    # Force a proper rotation: flip the weakest direction if the best orthogonal map reflects.
    sign = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    dmat = np.diag([1.0, 1.0, sign])
    r = vt.T @ dmat @ u.T
    t = cd - r @ cs
    res = np.linalg.norm(s @ r.T + t - d, axis=1)
    return RigidFit(rotation=r, translation=t, rms_mm=float(np.sqrt(np.mean(res**2))), max_residual_mm=float(res.max()))


class _Surface:
    """Closest points on a triangle mesh without rtree: exact brute force on small meshes,
    else exact distance to the k triangles with the nearest centroids (adequate for CAD meshes
    whose triangles are small against the probe spacing)."""

    def __init__(self, mesh: trimesh.Trimesh, k: int = 24) -> None:
        import trimesh  # heavy import only when a mesh is used

        self._tri = np.asarray(mesh.triangles, dtype=float)
        if len(self._tri) == 0:
            raise InputError("ICP: the CAD mesh has no triangles")
        nrm = np.cross(self._tri[:, 1] - self._tri[:, 0], self._tri[:, 2] - self._tri[:, 0])
        self.normals = nrm / np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-300)
        self._closest: Callable[[F, F], F] = trimesh.triangles.closest_point
        self._k = min(k, len(self._tri))
        self._tree = cKDTree(self._tri.mean(axis=1)) if len(self._tri) > 64 else None

    def closest(self, pts: F) -> tuple[F, F]:
        """Closest surface points and the unit normals of their triangles."""
        m = len(pts)
        if self._tree is None:
            nt = len(self._tri)
            idx = np.broadcast_to(np.arange(nt), (m, nt))
        else:
            _, idx = self._tree.query(pts, k=self._k)
            idx = np.atleast_2d(idx)
            nt = idx.shape[1]
        tri = self._tri[idx.ravel()]
        q = np.repeat(pts, nt, axis=0)
        cp = self._closest(tri, q).reshape(m, nt, 3)
        d2 = np.sum((cp - pts[:, None, :]) ** 2, axis=2)
        best = np.argmin(d2, axis=1)
        rows = np.arange(m)
        return cp[rows, best], self.normals[idx[rows, best]]


def _point_to_plane_step(p: F, q: F, n: F) -> F:
    """Linearised rigid step (4×4) minimising Σ((R·p + t − q)·n)²: fast on flat-faced parts."""
    a = np.hstack([np.cross(p, n), n])
    b = -np.sum((p - q) * n, axis=1)
    x, *_ = np.linalg.lstsq(a, b, rcond=1e-10)
    w, t = x[:3], x[3:]
    ang = float(np.linalg.norm(w))
    r = np.eye(3) if ang == 0.0 else rotation_matrix(w / ang, np.degrees(ang))
    # Re-centre the translation: the linearisation rotates about the origin.
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = t
    return m


def icp(points: ArrayLike, mesh: trimesh.Trimesh, *, initial: ArrayLike | None = None, max_iterations: int = 50,
        tolerance_mm: float = 1e-9) -> RigidFit:
    """Rigid transform that carries the CAD mesh onto the probed points (CAD → machine).

    Each probed point is paired with its closest point on the CAD surface; a point-to-plane
    step (a rigid motion: rotation by the exponential map, no scale, no reflection) moves the
    points, repeat until the RMS stops improving. `initial` is a 4×4 CAD → machine guess (e.g.
    from leveling, the face angle and 3-2-1); ICP only finds the nearest local minimum.
    """
    p = _pts(points, "ICP points")
    if len(p) < 3:
        raise InputError("ICP: needs at least 3 probed points")
    surf = _Surface(mesh)
    m = np.eye(4) if initial is None else np.asarray(initial, dtype=float).copy()
    # Track the machine → CAD map g = m⁻¹ and refine it on the probed points.
    g = np.linalg.inv(m)
    prev = np.inf
    it = 0
    converged = False
    for it in range(1, max_iterations + 1):  # noqa: B007  (`it` is reported after the loop)
        local = p @ g[:3, :3].T + g[:3, 3]
        cp, nrm = surf.closest(local)
        rms = float(np.sqrt(np.mean(np.sum((cp - local) ** 2, axis=1))))
        if prev - rms < tolerance_mm:
            converged = True
            break
        prev = rms
        g = _point_to_plane_step(local, cp, nrm) @ g
    m = np.linalg.inv(g)
    local = p @ g[:3, :3].T + g[:3, 3]
    cp, _ = surf.closest(local)
    res = np.linalg.norm(cp - local, axis=1)
    # Re-orthonormalise the rotation against round-off.
    u, _, vt = np.linalg.svd(m[:3, :3])
    return RigidFit(rotation=u @ vt, translation=m[:3, 3].copy(), rms_mm=float(np.sqrt(np.mean(res**2))),
                    max_residual_mm=float(res.max()), iterations=it, converged=converged)
