"""What every program export needs from a job: passes in the frame the machine works in.

Pure: a typed job (controller/job/read.py) in, frozen dataclasses out. The alignment (docs/contract.md §3,
`"alignment": {"transform": 4×4 part→machine}`) is carried here once, for every format.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from controller.job.model import CellJob
from core.errors import InputError

VERTICAL = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True, eq=False)
class ProgramPass:
    """One arc-on bead as a program sees it."""

    layer: int            # the job's layer index
    index: int            # the pass's index within its layer
    role: str
    width_mm: float
    current_a: float
    speed_mm_min: float
    wfs_m_min: float
    points: np.ndarray    # (n, 3) in the part frame (the job's frame)
    axes: np.ndarray      # (n, 3) unit tool axes in the part frame (+Z: vertical torch)
    five_axis: bool       # the job gave tool axes for this pass
    speeds: np.ndarray | None = None   # (n - 1,) mm/min per segment (a cell-job/2 pass), else None
    wfs: np.ndarray | None = None      # (n - 1,) m/min per segment (a cell-job/2 pass), else None

    def segment_speeds(self) -> np.ndarray:
        """(n - 1,) mm/min: every segment's travel speed (the pass's one when it has no array)."""
        return self.speeds if self.speeds is not None else np.full(len(self.points) - 1, self.speed_mm_min)

    def segment_wfs(self) -> np.ndarray:
        """(n - 1,) m/min: every segment's wire feed (the pass's one when it has no array)."""
        return self.wfs if self.wfs is not None else np.full(len(self.points) - 1, self.wfs_m_min)


@dataclass(frozen=True, eq=False)
class Program:
    """The job's passes in order, the per-layer interpass dwell and the alignment."""

    name: str
    source: str
    sha256: str
    material: str
    passes: tuple[ProgramPass, ...]
    layer_dwell_s: dict[int, float]   # interpass dwell before each layer (the first: none)
    transform: np.ndarray             # 4×4 part→machine (identity without an alignment)
    aligned: bool

    def machine(self, p: ProgramPass) -> tuple[np.ndarray, np.ndarray]:
        """A pass's points and tool axes in the machine frame (the alignment applied)."""
        r, t = self.transform[:3, :3], self.transform[:3, 3]
        return p.points @ r.T + t, p.axes @ r.T

    @property
    def five_axis(self) -> bool:
        return any(p.five_axis for p in self.passes)


def alignment_matrix(job: CellJob) -> np.ndarray | None:
    """The job's part→machine transform, or None; InputError when it is not a rigid 4×4."""
    al = job.alignment
    if al is None:
        return None
    if al.transform is None:
        raise InputError("job file: alignment.transform must be a 4×4 matrix of numbers")
    m = al.transform
    r = m[:3, :3]
    if not np.allclose(r.T @ r, np.eye(3), atol=1e-6) or np.linalg.det(r) < 0:
        raise InputError("job file: alignment.transform is not a rotation plus translation")
    return m


def points_in_machine_frame(job: CellJob) -> bool:
    """Whether the job's points were already moved by its alignment (`cell align run --job`)."""
    return job.alignment is not None and job.alignment.points_in_machine_frame


def _axes(a: np.ndarray | None) -> np.ndarray | None:
    """A pass's tool axes as exact unit vectors (the file's are unit within 1e-3: planner.job)."""
    if a is None:
        return None
    unit: np.ndarray = a / np.linalg.norm(a, axis=1)[:, None]
    return unit


def build_program(job: CellJob, *, name: str) -> Program:
    """Lay out the job's passes in the part frame, with the alignment beside them."""
    parsed = job.job
    m = alignment_matrix(job)
    t = m if m is not None else np.eye(4)
    # Old-style aligned jobs carry moved points: bring them back to the part frame, so that
    # every format applies the alignment exactly once (G-code in the points, robots as a frame).
    back = np.linalg.inv(t) if m is not None and points_in_machine_frame(job) else None
    passes: list[ProgramPass] = []
    dwell: dict[int, float] = {}
    for li, layer in enumerate(parsed.layers):
        if li > 0:
            dwell[layer.index] = float(layer.interpass.dwell_s) if layer.interpass else 0.0
        for pi, p in enumerate(layer.passes):
            pts = np.asarray(p.points, dtype=np.float64)
            given = _axes(p.axes)
            axes = given if given is not None else np.tile(VERTICAL, (len(pts), 1))
            if back is not None:
                pts = pts @ back[:3, :3].T + back[:3, 3]
                if given is not None:
                    axes = axes @ back[:3, :3].T
            passes.append(ProgramPass(layer.index, pi, p.role, p.width_mm, p.current_a, p.speed_mm_min,
                                      p.wfs_m_min, pts, axes, given is not None, p.seg_speed_mm_min, p.seg_wfs_m_min))
    mat = parsed.material.get("name", "") if isinstance(parsed.material, dict) else ""
    return Program(name=name, source=parsed.source.file, sha256=parsed.source.sha256, material=str(mat),
                   passes=tuple(passes), layer_dwell_s=dwell, transform=t, aligned=m is not None)


@dataclass(frozen=True, eq=False)
class RobotPass:
    """A pass read back from a robot program (RAPID or KRL): what the round-trip checks compare."""

    layer: int
    index: int
    role: str
    width_mm: float
    speed_mm_min: float
    wfs_m_min: float
    current_a: float
    points: np.ndarray
    axes: np.ndarray
    speeds: np.ndarray | None = None   # (n - 1,) mm/min of each weld move as the program gives it
    wfs: np.ndarray | None = None      # (n - 1,) m/min of each weld move as the program gives it
