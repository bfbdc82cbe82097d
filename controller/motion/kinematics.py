"""Rigid transforms of the alignment: the paper's table transform, A/B and A/C trunnion kinematics.

Conventions (Padathu 2005, appendix; docs/contract.md §4):

* A table rotation is applied to a point as ``W = T(-P)·R_outer·R_inner·T(P)·p``: a rotation
  about the point ``-P``. In the paper's own example A turns about z and B about y, A first.
* Trunnion tables: the *inner* axis carries the part and is applied first, the *outer* axis
  carries the inner one. Table ``AB``: A (``axis_a``) inner, B (``axis_second``) outer, exactly the
  paper's ``R_B·R_A``. Table ``AC``: C (``axis_second``) is the rotary plate on the A trunnion, so
  C is inner and A outer: ``R_A·R_C``. The outer axis passes through ``-P``; the inner axis
  through ``-P + offset`` (``offset_mm``: the distance between the two axes at zero).
* The tool is fixed and points along machine -Z; a tool direction is given as the unit vector
  from the surface toward the tool, which the table must bring to machine +Z.

Everything here is pure: numpy in, frozen dataclasses / arrays out.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Iterable, Mapping, Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from controller.job.model import CellJob
from controller.job.read import JobDoc, edited
from core.config import Kinematics
from core.errors import InputError

if TYPE_CHECKING:  # trimesh loads on first use (start-up time)
    import trimesh

F = NDArray[np.float64]
_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


def unit(v: ArrayLike) -> F:
    v = np.asarray(v, dtype=float)
    n = float(np.linalg.norm(v))
    if not np.isfinite(n) or n == 0.0:
        raise InputError(f"direction {v.tolist()} has no length; give a non-zero vector")
    return v / n


def axis_vector(axis: str | ArrayLike) -> F:
    """'x'/'y'/'z' (or '-x' …) or a 3-vector → unit vector."""
    if isinstance(axis, str):
        s = axis.strip().lower()
        sign = -1.0 if s.startswith("-") else 1.0
        key = s.lstrip("+-")
        if key not in _AXES:
            raise InputError(f"axis '{axis}' is not one of x, y, z")
        return sign * np.array(_AXES[key])
    return unit(axis)


def rotation_matrix(axis: str | ArrayLike, angle_deg: float) -> F:
    """3×3 right-handed rotation about a unit axis (Rodrigues)."""
    k = axis_vector(axis)
    t = np.radians(angle_deg)
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    r: F = np.eye(3) + np.sin(t) * kx + (1.0 - np.cos(t)) * (kx @ kx)
    return r


def homogeneous(rotation: ArrayLike | None = None, translation: ArrayLike | None = None) -> F:
    m = np.eye(4)
    if rotation is not None:
        m[:3, :3] = np.asarray(rotation, dtype=float)
    if translation is not None:
        m[:3, 3] = np.asarray(translation, dtype=float)
    return m


def translation(t: ArrayLike) -> F:
    return homogeneous(None, t)


def apply_transform(matrix: ArrayLike, points: ArrayLike) -> F:
    """Apply a 4×4 transform to an (n, 3) array (or one 3-vector) of points."""
    m = np.asarray(matrix, dtype=float)
    p = np.asarray(points, dtype=float)
    out: F = p @ m[:3, :3].T + m[:3, 3]
    return out


def rotate_vectors(matrix: ArrayLike, vectors: ArrayLike) -> F:
    """Rotate directions (no translation) by the rotation part of a 4×4 transform."""
    m = np.asarray(matrix, dtype=float)
    out: F = np.asarray(vectors, dtype=float) @ m[:3, :3].T
    return out


# --- the paper's appendix ------------------------------------------------------------------------


def paper_matrices(a_deg: float, b_deg: float) -> tuple[F, F]:
    """R_A (about z by A) and R_B (about y by B) as 4×4, with the appendix's cos(phi) typo fixed.

    The appendix writes ``RB[3,3] = cos(phi)`` (phi is A); it must be ``cos(theta)`` (theta is B),
    else R_B is not a rotation as soon as A ≠ B.
    """
    phi, theta = np.radians(a_deg), np.radians(b_deg)
    ra = np.array([[np.cos(phi), -np.sin(phi), 0, 0], [np.sin(phi), np.cos(phi), 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    rb = np.array([[np.cos(theta), 0, np.sin(theta), 0], [0, 1, 0, 0], [-np.sin(theta), 0, np.cos(theta), 0], [0, 0, 0, 1.0]])
    return ra, rb


def paper_transform(points: ArrayLike, a_deg: float, b_deg: float, pivot: ArrayLike) -> F:
    """The paper's ``W = T(-P)·R_B·R_A·T(P)·p`` for (n, 3) points (Table 1: A = B = 45°, P = (1, 1, 5))."""
    ra, rb = paper_matrices(a_deg, b_deg)
    p = np.asarray(pivot, dtype=float)
    return apply_transform(translation(-p) @ rb @ ra @ translation(p), points)


def rotation_about_pivot(rotations: Sequence[tuple[str | ArrayLike, float]], pivot: ArrayLike) -> F:
    """4×4 of ``T(-P)·R_n···R_1·T(P)``: rotations applied in the order given, about the point -P."""
    r = np.eye(4)
    for axis, deg in rotations:
        r = homogeneous(rotation_matrix(axis, deg)) @ r
    p = np.asarray(pivot, dtype=float)
    return translation(-p) @ r @ translation(p)


# --- trunnion tables -----------------------------------------------------------------------------


def signed_angle(v: F, w: F, axis: F) -> float:
    """Angle (rad) that turns v into w about axis, both projected on the plane normal to axis."""
    vp = v - axis * (v @ axis)
    wp = w - axis * (w @ axis)
    return float(np.arctan2(axis @ np.cross(vp, wp), vp @ wp))


def two_axis_solutions(v: ArrayLike, target: ArrayLike, inner: ArrayLike, outer: ArrayLike) -> list[tuple[float, float]]:
    """All (inner, outer) angles in degrees with ``R(outer, t2)·R(inner, t1)·v = target`` (Paden–Kahan 2).

    Empty when no rotation pair reaches the target (the cones about the two axes do not meet).
    """
    v, target, u1, u2 = unit(v), unit(target), unit(inner), unit(outer)
    # c is the intermediate direction: R(u1, t1) v = c = R(u2, -t2) target.
    d = float(u1 @ u2)
    w = np.cross(u1, u2)
    ww = float(w @ w)
    if ww < 1e-18:
        raise InputError("the two table axes are parallel; check kinematics.axis_a / axis_second")
    s1, s2 = float(u1 @ v), float(u2 @ target)
    det = 1.0 - d * d
    alpha = (s1 - d * s2) / det
    beta = (s2 - d * s1) / det
    g2 = (1.0 - alpha * alpha - beta * beta - 2.0 * alpha * beta * d) / ww
    if g2 < -1e-12:
        return []
    gs = [0.0] if g2 <= 1e-24 else [np.sqrt(g2), -np.sqrt(g2)]
    out = []
    for g in gs:
        c = alpha * u1 + beta * u2 + g * w
        t1 = signed_angle(v, c, u1)
        t2 = signed_angle(c, target, u2)
        out.append((float(np.degrees(t1)), float(np.degrees(t2))))
    return out


@dataclass(frozen=True)
class Trunnion:
    """A two-axis tilting table: which axes, in which order, about which pivot."""

    table: str = "AB"                              # AB | AC
    pivot: tuple[float, float, float] = (0.0, 0.0, 0.0)  # P: the outer axis passes through -P
    axis_a: tuple[float, float, float] = (1.0, 0.0, 0.0)
    axis_second: tuple[float, float, float] = (0.0, 1.0, 0.0)  # B (AB table) or C (AC table)
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)  # inner axis point = -P + offset
    a_limits_deg: tuple[float, float] = (-120.0, 120.0)
    second_limits_deg: tuple[float, float] = (-360.0, 360.0)
    chord_tolerance_mm: float = 0.02              # 5-axis moves split until the tip stays this close

    @classmethod
    def from_config(cls, kin: Kinematics) -> "Trunnion":
        """From core.config.Kinematics (cell.yaml `kinematics:`)."""
        return cls(table=kin.table, pivot=kin.pivot_mm, axis_a=kin.axis_a,
                   axis_second=kin.axis_second, offset=kin.offset_mm,
                   a_limits_deg=kin.a_limits_deg, second_limits_deg=kin.second_limits_deg,
                   chord_tolerance_mm=kin.chord_tolerance_mm)

    # (inner axis, outer axis) as unit vectors; angles are always reported as (a, second).
    def axes(self) -> tuple[F, F]:
        """(inner axis, outer axis) of the table as unit vectors."""
        if self.table == "AB":
            return unit(self.axis_a), unit(self.axis_second)
        if self.table == "AC":
            return unit(self.axis_second), unit(self.axis_a)
        raise InputError(f"kinematics.table '{self.table}' is not AB or AC")

    def _inner_outer_deg(self, a_deg: float, second_deg: float) -> tuple[float, float]:
        return (a_deg, second_deg) if self.table == "AB" else (second_deg, a_deg)

    def matrix(self, a_deg: float, second_deg: float) -> F:
        """4×4 taking table (part) coordinates to machine coordinates at these table angles."""
        u1, u2 = self.axes()
        t1, t2 = self._inner_outer_deg(a_deg, second_deg)
        p = np.asarray(self.pivot, dtype=float)
        c2 = -p
        c1 = -p + np.asarray(self.offset, dtype=float)
        inner = translation(c1) @ homogeneous(rotation_matrix(u1, t1)) @ translation(-c1)
        outer = translation(c2) @ homogeneous(rotation_matrix(u2, t2)) @ translation(-c2)
        return outer @ inner

    def within_limits(self, a_deg: float, second_deg: float) -> bool:
        lo, hi = self.a_limits_deg
        lo2, hi2 = self.second_limits_deg
        return lo - 1e-9 <= a_deg <= hi + 1e-9 and lo2 - 1e-9 <= second_deg <= hi2 + 1e-9

    def orient(self, direction: ArrayLike, target: ArrayLike = (0.0, 0.0, 1.0)) -> tuple[float, float]:
        """Table angles (a, second) in degrees that turn a part direction onto `target` (+Z).

        Of the (up to two) solutions within the axis limits, the one with the smallest
        largest rotation: for a nearly level face that is the unique small-angle solution.
        """
        u1, u2 = self.axes()
        sols = []
        for t1, t2 in two_axis_solutions(direction, target, u1, u2):
            a, s = (t1, t2) if self.table == "AB" else (t2, t1)
            if self.within_limits(a, s):
                sols.append((max(abs(a), abs(s)), abs(a) + abs(s), a, s))
        if not sols:
            raise InputError(
                f"no {self.table} table angles within the limits bring direction "
                f"{np.round(unit(direction), 6).tolist()} to {np.asarray(target, dtype=float).tolist()}; check kinematics in cell.yaml")
        sols.sort()
        return sols[0][2], sols[0][3]

    def forward(self, axes: ArrayLike) -> tuple[F, F]:
        """Machine axes (x, y, z, a, second) → (part point under the tool, tool direction in the part)."""
        x, y, z, a, s = (float(v) for v in np.asarray(axes, dtype=float))
        m = self.matrix(a, s)
        inv = np.linalg.inv(m)
        point = apply_transform(inv, np.array([x, y, z]))
        tool = m[:3, :3].T @ np.array([0.0, 0.0, 1.0])
        return point, tool

    def inverse(self, point: ArrayLike, tool: ArrayLike) -> F:
        """(part point, tool direction in the part) → machine axes (x, y, z, a, second)."""
        a, s = self.orient(tool)
        xyz = apply_transform(self.matrix(a, s), np.asarray(point, dtype=float))
        return np.array([xyz[0], xyz[1], xyz[2], a, s])


# --- applying an alignment -------------------------------------------------------------------------


def apply_to_job(job: CellJob, matrix: ArrayLike, record: Mapping[str, object] | None = None, *,
                 name: str | None = None) -> CellJob:
    """A copy of a job moved by `matrix` (points, normals, axes), recording the alignment (and
    `name`, when given). The copy is a new job, read as its file would be (its own hash).

    A job holds at most one alignment (docs/contract.md §3): a job that already carries one is refused.
    """
    m = np.asarray(matrix, dtype=float)
    if m.shape != (4, 4):
        raise InputError(f"alignment transform must be 4×4, got shape {m.shape}")
    if job.alignment is not None:
        raise InputError("the job already carries an alignment; a second one is refused: align the original "
                         "(unaligned) job instead")

    def move(out: JobDoc) -> JobDoc:
        out["alignment"] = dict(record) if record else {"transform": m.tolist()}
        out["alignment"].setdefault("transform", m.tolist())
        if name is not None:
            out["name"] = name
        for layer in out["layers"]:
            for ps in layer["passes"]:
                ps["points"] = apply_transform(m, np.asarray(ps["points"], dtype=float)).tolist()
                if ps.get("normals"):
                    ps["normals"] = rotate_vectors(m, np.asarray(ps["normals"], dtype=float)).tolist()
                if ps.get("axes"):
                    ps["axes"] = rotate_vectors(m, np.asarray(ps["axes"], dtype=float)).tolist()
        return out

    return edited(job, move, f"the aligned job {name or job.name}")


def apply_to_mesh(mesh: trimesh.Trimesh, matrix: ArrayLike) -> trimesh.Trimesh:
    """A transformed copy of a trimesh mesh (the original is left as it is)."""
    out: trimesh.Trimesh = mesh.copy()
    out.apply_transform(np.asarray(matrix, dtype=float))
    return out


def parse_rotations(specs: Iterable[str]) -> list[tuple[str, float]]:
    """'z:45' words → [(axis, degrees)]; errors name the bad word."""
    out = []
    for spec in specs:
        axis, sep, deg = spec.partition(":")
        if not sep:
            raise InputError(f"--rotate '{spec}': expected AXIS:DEG, e.g. z:45")
        axis_vector(axis)
        try:
            val = float(deg)
        except ValueError:
            raise InputError(f"--rotate '{spec}': '{deg}' is not a number of degrees") from None
        if not np.isfinite(val):
            raise InputError(f"--rotate '{spec}': angle must be finite")
        out.append((axis.strip().lower(), val))
    return out
