"""The alignment's geometry without a cell (`cell align plane/transform/run`, the demo): a plane
fitted to probed points and the A/B angles that level it, points rotated about a pivot, the probe
plan on a part's CAD, an alignment as the record a job carries and its report files."""
from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any, Iterable

import numpy as np
from numpy.typing import ArrayLike

from core.config import CellConfig, Workpiece

if TYPE_CHECKING:
    from controller.align.fit import PlaneFit
    from controller.align.leveling import Leveling
    from controller.align.routine import AlignResult, ProbePlan

__all__ = ["alignment_record", "fit_and_level", "probe_plan_on", "read_rotations", "rotate_points", "write_align_report"]


def fit_and_level(points: ArrayLike, cfg: CellConfig, *, noise_mm: float | None,
                  reject: bool = True) -> tuple[PlaneFit, Leveling]:
    """A plane fitted to probed points (SVD, χ² against `noise_mm`, outliers rejected unless
    `reject` is False) and the table angles of `cfg`'s trunnion that bring its normal to +Z."""
    # lazy: the fits (scipy) load only when points are fitted
    from controller.align.fit import fit_plane
    from controller.align.leveling import leveling_angles
    from controller.motion.kinematics import Trunnion

    fit = fit_plane(points, noise_mm=noise_mm, reject=reject)
    return fit, leveling_angles(fit.normal, Trunnion.from_config(cfg.kinematics))


def read_rotations(words: Iterable[str]) -> list[tuple[str, float]]:
    """'axis:deg' words (`z:45`) as (axis, degrees); a bad word is an InputError naming it."""
    # lazy: the kinematics load only when points are moved
    from controller.motion.kinematics import parse_rotations

    return parse_rotations(words)


def rotate_points(rotations: list[tuple[str, float]], pivot: ArrayLike, points: ArrayLike) -> tuple[np.ndarray, np.ndarray]:
    """The rotations applied in order about the point -`pivot` (Padathu's W = T(-P)·R·T(P)·p): the
    4×4 matrix and the moved points."""
    # lazy: the kinematics load only when points are moved
    from controller.motion.kinematics import apply_transform, rotation_about_pivot

    m = rotation_about_pivot(rotations, pivot)
    return m, apply_transform(m, points)


def probe_plan_on(workpiece: Workpiece | None, cad_path: str | Path | None = None,
                  base_dir: Path | None = None) -> ProbePlan:
    """The alignment routine's touches on the nominal part: `cad_path`, else the workpiece's mesh
    (or its block), a relative path from `base_dir`."""
    # lazy: the alignment routine (ICP, trimesh) loads only when a cell is aligned
    from controller.align.routine import cad_mesh, plan_for_mesh

    return plan_for_mesh(cad_mesh(workpiece, cad_path, base_dir))


def alignment_record(res: AlignResult) -> dict[str, Any]:
    """The `alignment` section a job carries of an alignment (transform, A/B, when it was probed)."""
    # lazy: the alignment routine loads only when a cell is aligned
    from controller.align.routine import alignment_record as record

    return record(res)


def write_align_report(res: AlignResult, out_dir: str | Path) -> dict[str, Path]:
    """DIR/align.json and DIR/align.png of an alignment; their paths by kind (json, png)."""
    # lazy: matplotlib loads only when a report is written
    from controller.align.report import write_report

    return write_report(res, out_dir)
