"""The CNC simulator's virtual workpiece: a mesh on the rotary table that the touch probe hits.

Frames (all mm, right-handed):
- part frame: the mesh's own coordinates. With `mesh: null` the part is a block of `size_mm`
  centred on the table axis in X and Y with its TOP face at z = 0 (so it spans z ∈ [-h, 0]);
  a mesh file is used in its own coordinates (loaded with trimesh, unit mm).
- table frame: the part as clamped on the table, `pose = T(offset) · R_y(tilt_b) · R_x(tilt_a) ·
  R_z(rotation_c)`: spun about Z first, then tilted about X, then about Y, then shifted.
- machine frame: the table frame turned by the machine's rotary axes A and B (or C) with the
  cell's trunnion kinematics (sims/table_kin.py, the convention of docs/kinematics.md: AB is
  `R_B·R_A`, AC is `R_A·R_C`, about −P). The probe tip sits at the machine position X, Y, Z.

Probe contact is a segment–mesh intersection (Möller–Trumbore, vectorised over triangles; no
rtree needed), and against the deposit's height map (sims/heightmap.py: the World's, in the
part frame, when the simulators run with process physics), with Gaussian trigger noise of σ = `probe_noise_mm` along the travel direction
from a seeded generator, so a run is reproducible.
"""
from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Callable

import numpy as np

from sims.heightmap import HeightMap
from sims.pour import FloatArray
from sims.table_kin import TableKin, rot, trans

if TYPE_CHECKING:
    from core.config import Kinematics, Workpiece as WorkpieceConfig

__all__ = ["Workpiece", "rot", "trans"]

_EPS = 1e-12


def _vec3(v: Sequence[float] | np.ndarray) -> tuple[float, float, float]:
    return (float(v[0]), float(v[1]), float(v[2]))


class Workpiece:
    """A triangle mesh posed on the table; answers probe segments and "is the tip touching"."""

    def __init__(
        self,
        triangles: np.ndarray,
        pose: np.ndarray,
        *,
        noise_mm: float = 0.0,
        seed: int = 0,
        pivot_mm: tuple[float, float, float] = (0.0, 0.0, 0.0),
        axis_a: tuple[float, float, float] = (1.0, 0.0, 0.0),
        axis_second: tuple[float, float, float] = (0.0, 1.0, 0.0),
        trigger_mm: float | None = None,
        table: str = "AB",
        offset_mm: tuple[float, float, float] = (0.0, 0.0, 0.0),
    ) -> None:
        tri = np.asarray(triangles, dtype=float).reshape(-1, 3, 3)
        if len(tri) == 0:
            raise ValueError("workpiece mesh has no triangles")
        self._v0 = tri[:, 0]
        self._e1 = tri[:, 1] - tri[:, 0]
        self._e2 = tri[:, 2] - tri[:, 0]
        self.pose = np.asarray(pose, dtype=float)
        self.noise_mm = float(noise_mm)
        self.rng = np.random.default_rng(seed)
        self.pivot = np.asarray(pivot_mm, dtype=float)
        self.axis_a = axis_a
        self.axis_second = axis_second
        # deposited metal: the World's height map of this device, in the part frame (when served
        # with process physics; sims/process_world.py)
        self.deposit_map: HeightMap | None = None
        self.settle: Callable[[], object] | None = None   # lays the World's deferred beads first
        self.kin = TableKin(table, _vec3(self.pivot), _vec3(axis_a), _vec3(axis_second), _vec3(offset_mm))
        # How close to the surface the stylus counts as deflected (a real probe trips within
        # microns); wide enough that a noisy trip point still reads as tripped.
        self.trigger_mm = trigger_mm if trigger_mm is not None else max(0.01, 5.0 * self.noise_mm)

    # -- construction -----------------------------------------------------------------------
    @classmethod
    def from_config(cls, wp: WorkpieceConfig, noise_mm: float, *, seed: int = 0, kinematics: Kinematics | None = None,
                    base_dir: Path | None = None) -> "Workpiece":
        """From sim.yaml's `cnc.workpiece` (core.config.Workpiece) and cell.yaml's kinematics."""
        # lazy: trimesh loads only when this path runs (start-up time)
        import trimesh

        if wp.mesh:
            p = Path(wp.mesh)
            if not p.is_absolute() and base_dir is not None and (base_dir / p).exists():
                p = base_dir / p
            mesh = trimesh.load_mesh(str(p), force="mesh")
        else:
            sx, sy, sz = wp.size_mm
            mesh = trimesh.creation.box(extents=(sx, sy, sz))
            mesh.apply_translation((0.0, 0.0, -sz / 2.0))  # top face at z = 0
        pose = (trans(wp.offset_mm) @ rot((0, 1, 0), wp.tilt_b_deg) @ rot((1, 0, 0), wp.tilt_a_deg)
                @ rot((0, 0, 1), wp.rotation_c_deg))
        if kinematics is None:
            return cls(np.asarray(mesh.triangles), pose, noise_mm=noise_mm, seed=seed)
        return cls(np.asarray(mesh.triangles), pose, noise_mm=noise_mm, seed=seed,
                   pivot_mm=_vec3(kinematics.pivot_mm), axis_a=_vec3(kinematics.axis_a),
                   axis_second=_vec3(kinematics.axis_second), table=str(kinematics.table),
                   offset_mm=_vec3(kinematics.offset_mm))

    # -- frames -----------------------------------------------------------------------------
    def table_matrix(self, a_deg: float, second_deg: float) -> np.ndarray:
        """Table frame → machine frame for rotary positions A and B/C (docs/kinematics.md)."""
        return self.kin.matrix(a_deg, second_deg)

    def part_to_machine(self, a_deg: float = 0.0, second_deg: float = 0.0) -> np.ndarray:
        m: np.ndarray = self.table_matrix(a_deg, second_deg) @ self.pose
        return m

    def _to_part(self, pts: np.ndarray, a_deg: float, second_deg: float) -> np.ndarray:
        inv = np.linalg.inv(self.part_to_machine(a_deg, second_deg))
        pts = np.asarray(pts, dtype=float).reshape(-1, 3)
        out: np.ndarray = pts @ inv[:3, :3].T + inv[:3, 3]
        return out

    def vertices(self) -> np.ndarray:
        """Every triangle corner of the mesh (part frame), (3n, 3)."""
        out: np.ndarray = np.concatenate([self._v0, self._v0 + self._e1, self._v0 + self._e2])
        return out

    # -- the deposit -------------------------------------------------------------------------
    def top_z(self, xs: FloatArray, ys: FloatArray) -> FloatArray:
        """The mesh's highest surface over each (x, y) of the part frame (NaN where none): the
        substrate under the deposit's height map."""
        x = np.asarray(xs, dtype=float).reshape(-1, 1)
        y = np.asarray(ys, dtype=float).reshape(-1, 1)
        v0, e1, e2 = self._v0, self._e1, self._e2
        det = e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0]
        ok = np.abs(det) > _EPS
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        px, py = x - v0[:, 0], y - v0[:, 1]
        u = (px * e2[:, 1] - py * e2[:, 0]) * inv
        v = (py * e1[:, 0] - px * e1[:, 1]) * inv
        hit = ok & (u >= -1e-12) & (v >= -1e-12) & (u + v <= 1 + 1e-12)
        z = v0[:, 2] + u * e1[:, 2] + v * e2[:, 2]
        z = np.where(hit, z, -np.inf).max(axis=1)
        out: FloatArray = np.where(np.isfinite(z), z, np.nan)
        return out

    def part_frame(self, pos5: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
        """The tool tip (machine X Y Z at rotary A, B|C) and the tool axis, in the workpiece frame."""
        inv = np.linalg.inv(self.part_to_machine(float(pos5[3]), float(pos5[4])))
        q = inv[:3, :3] @ np.asarray(pos5[:3], dtype=float) + inv[:3, 3]
        return q, inv[:3, :3] @ np.array([0.0, 0.0, 1.0])

    # -- geometry ---------------------------------------------------------------------------
    def _ray_hits(self, origin: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """Ray parameters t of every triangle the ray (origin + t·direction) crosses."""
        v0, e1, e2 = self._v0, self._e1, self._e2
        pvec = np.cross(direction, e2)
        det = np.einsum("ij,ij->i", e1, pvec)
        ok = np.abs(det) > _EPS
        inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
        tvec = origin - v0
        u = np.einsum("ij,ij->i", tvec, pvec) * inv
        qvec = np.cross(tvec, e1)
        v = (qvec @ direction) * inv
        t = np.einsum("ij,ij->i", e2, qvec) * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1)
        out: np.ndarray = t[hit]
        return out

    def surface_hit(self, p0: Sequence[float], p1: Sequence[float], a_deg: float = 0.0, second_deg: float = 0.0) -> float | None:
        """Distance along p0→p1 (machine frame) to the first surface crossing, or None."""
        q0, q1 = self._to_part(np.array([p0, p1], dtype=float)[:, :3], a_deg, second_deg)
        d = q1 - q0
        length = float(np.linalg.norm(d))
        if length < 1e-12:
            return None
        t = np.sort(self._ray_hits(q0, d / length))
        t = t[(t >= -1e-9) & (t <= length + 1e-9)]
        dm = self.deposit_map
        if dm is not None and dm.carved.any():   # the mesh's faces where a cutter took them away
            t = np.array([x for x in t if not dm.cut_away(q0 + d / length * x)])
        best = float(t.min()) if len(t) else None
        if dm is not None:
            if self.settle is not None:
                self.settle()
            dep = dm.ray_hit(q0, q1)
            if dep is not None and (best is None or dep < best):
                best = dep
        return best

    def inside(self, p: Sequence[float], a_deg: float = 0.0, second_deg: float = 0.0) -> bool:
        """Is the machine-frame point inside the (watertight) part? Parity of ray crossings."""
        q = self._to_part(np.asarray(p, dtype=float)[:3], a_deg, second_deg)[0]
        d = np.array([0.2672612, 0.5345225, 0.8017837])  # skewed: avoids hitting edges exactly
        if self.deposit_map is not None and self.deposit_map.inside(q):
            return True
        if self.deposit_map is not None and self.deposit_map.cut_away(q):
            return False
        t = self._ray_hits(q, d)  # parity over the (closed) mesh
        return bool(np.count_nonzero(t > 1e-9) % 2)

    def probe(self, p0: Sequence[float], p1: Sequence[float], a_deg: float = 0.0, second_deg: float = 0.0) -> tuple[float, float, float] | None:
        """Where a probe moving p0→p1 trips (with noise), or None when it reaches p1 untouched."""
        dist = self.surface_hit(p0, p1, a_deg, second_deg)
        if dist is None:
            return None
        p0a = np.asarray(p0, dtype=float)[:3]
        d = np.asarray(p1, dtype=float)[:3] - p0a
        length = float(np.linalg.norm(d))
        if self.noise_mm > 0:
            dist = dist + float(self.rng.normal(0.0, self.noise_mm))
        dist = min(max(dist, 0.0), length)
        p = p0a + d / length * dist
        return (float(p[0]), float(p[1]), float(p[2]))
