"""Reading a job (cell-job/1 JSON) once, at the edge: a file, an object built in memory, or the
copy a journal holds, checked by planner.job.load_job and returned typed as a `CellJob`.

This is the only place of the controller that sees the file's JSON. The job's hash (what the
journal and the run directory are keyed on) is computed here from the object as read
(controller/job/identity.py) and carried with the typed job. Every error names the file (or the
journal) and the field, as an InputError (exit 2, one `error:` line).
"""
from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any, Callable, Required, TypedDict

import numpy as np

from controller.job.identity import canonical_json, job_hash, job_name, text_hash
from controller.job.model import Alignment, CellJob, RepairInfo
from core.errors import InputError
from planner.job import load_job

MAX_PASSES = 200_000          # a 1 m³ part at 7 mm beads has ~60 000 passes
MAX_POINTS = 5_000_000        # points over the whole job (the planner's own: a few 100 000)
MAX_POINTS_PER_PASS = 1_000_000

_PREFIX = "job file: "


def read_job(path: str | Path) -> CellJob:
    """The job of a file; InputError naming the file (and the field) when it is not a good one."""
    p = Path(path)
    try:
        obj = json.loads(p.read_text(encoding="utf-8"))
    except UnicodeDecodeError as exc:
        raise InputError(f"{p}: not UTF-8 text (byte {exc.start}); not a cell-job/1 file") from None
    except RecursionError:
        raise InputError(f"{p}: nested too deeply; not a cell-job/1 file") from None
    except OSError as exc:
        raise InputError(f"{p}: cannot read the job ({exc.strerror or exc}); check the path") from None
    except json.JSONDecodeError as exc:
        raise InputError(f"{p}: line {exc.lineno}: not valid JSON ({exc.msg})") from None
    return job_from_dict(obj, str(p), path=p)


def job_from_dict(obj: Any, source: str = "job file", *, path: Path | None = None) -> CellJob:
    """The job of a parsed cell-job/1 object (a file's, or one built in memory: the demo's plan, an
    aligned copy); errors name `source` and the field. The object is not kept nor changed."""
    try:
        if not isinstance(obj, dict):
            raise InputError(f"{_PREFIX}not a cell-job/1 file")
        _bounded(obj)   # before anything is built from it
        job = load_job(obj)
        alignment, repair = _alignment(obj), _repair(obj)
    except InputError as exc:
        raise InputError(_named(str(exc), source)) from None
    text = canonical_json(obj)
    return CellJob(job=job, hash=text_hash(text), json=text, name=job_name(obj), path=path,
                   alignment=alignment, repair=repair)


def stored_job(job_json: str, stored_hash: str, journal: str | Path) -> CellJob:
    """The job a journal holds, refused when it no longer matches the checksum stored beside it."""
    try:
        obj = json.loads(job_json)
    except (ValueError, TypeError, RecursionError):
        raise InputError(f"journal {journal}: the job stored in it is not valid JSON (tampered or damaged); "
                         "it was left untouched") from None
    if not isinstance(obj, dict) or job_hash(obj) != stored_hash:
        raise InputError(f"journal {journal}: the job stored in it does not match its checksum "
                         f"{str(stored_hash)[:12]} (tampered); refusing to use it (the journal was left untouched)")
    return job_from_dict(obj, f"journal {journal}: the job stored in it")


class PassDoc(TypedDict, total=False):
    """A pass of a job file's object, as an edit sees it (the keys edits touch; the others kept as read)."""

    points: Required[list[list[float]]]
    normals: list[list[float]]
    axes: list[list[float]]


class LayerDoc(TypedDict):
    passes: list[PassDoc]


class JobDoc(TypedDict, total=False):
    """A job file's object, as an edit sees it (`edited`): what it may change is typed, the rest rides along."""

    layers: Required[list[LayerDoc]]
    name: str
    alignment: dict[str, object]


def edited(job: CellJob, edit: Callable[[JobDoc], JobDoc], source: str) -> CellJob:
    """A new job from `edit(obj)` on a copy of `job`'s object (it returns the edited object): an
    aligned copy, a renamed one. The copy is read like a file: its own hash and checks."""
    return job_from_dict(edit(json.loads(job.json)), source)


def _named(msg: str, source: str) -> str:
    """load_job's "job file: FIELD ..." with the file (or journal) named instead."""
    return f"{source}: {msg[len(_PREFIX):]}" if msg.startswith(_PREFIX) else f"{source}: {msg}"


def _bounded(obj: dict[str, Any]) -> None:
    """The pass and point counts bounded, so a hand-edited job can never exhaust memory or time
    (a malformed layer or pass is left to load_job, which names it)."""
    layers = obj.get("layers")
    n_pass = n_pts = 0
    for li, la in enumerate(layers if isinstance(layers, list) else []):
        passes = la.get("passes") if isinstance(la, dict) else None
        for pi, p in enumerate(passes if isinstance(passes, list) else []):
            n_pass += 1
            pts = p.get("points") if isinstance(p, dict) else None
            n = len(pts) if isinstance(pts, list) else 0
            if n > MAX_POINTS_PER_PASS:
                raise InputError(f"{_PREFIX}layers[{li}].passes[{pi}] has {n} points, over the limit "
                                 f"of {MAX_POINTS_PER_PASS}")
            n_pts += n
    if n_pass > MAX_PASSES:
        raise InputError(f"{_PREFIX}{n_pass} passes, over the limit of {MAX_PASSES}")
    if n_pts > MAX_POINTS:
        raise InputError(f"{_PREFIX}{n_pts} points, over the limit of {MAX_POINTS}")


def _number(v: Any) -> float | None:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
        return None
    return float(v)


def _matrix(v: Any, shape: tuple[int, int], what: str) -> np.ndarray | None:
    """`v` as a finite float array of `shape` (None stays None); InputError "job file: WHAT" otherwise."""
    if v is None:
        return None
    try:
        m = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{_PREFIX}{what}") from None
    if m.shape != shape or not np.all(np.isfinite(m)):
        raise InputError(f"{_PREFIX}{what}")
    return m


def _alignment(obj: dict[str, Any]) -> Alignment | None:
    al = obj.get("alignment")
    if not al:
        return None
    if not isinstance(al, dict):
        raise InputError(f"{_PREFIX}alignment must be an object")
    t = _matrix(al.get("transform"), (4, 4), "alignment.transform must be a 4x4 matrix of finite numbers")
    raw_table = al.get("table_deg")
    table: dict[str, Any] = raw_table if isinstance(raw_table, dict) else {}
    return Alignment(transform=t, table_a_deg=_number(table.get("a", al.get("level_a_deg"))),
                     table_b_deg=_number(table.get("b", al.get("level_b_deg"))),
                     probed_at=_number(al.get("probed_at")), no_level=bool(al.get("no_level")),
                     # old-style aligned jobs (no frame) carry points already moved by the transform
                     points_in_machine_frame=bool(al.get("points_in_machine_frame",
                                                         obj.get("frame") not in ("cad", "substrate"))))


def _repair(obj: dict[str, Any]) -> RepairInfo | None:
    rep = obj.get("repair")
    if rep is None:
        return None
    if not isinstance(rep, dict):
        raise InputError(f"{_PREFIX}repair must be an object")
    for key in ("cad", "stock"):
        if rep.get(key) is not None and not isinstance(rep[key], str):
            raise InputError(f"{_PREFIX}repair.{key} must be a file path")
    bounds = _matrix(rep.get("bounds_mm"), (2, 3),
                     "repair.bounds_mm must be [[x, y, z], [x, y, z]] (the repair volume's corners)")
    return RepairInfo(cad=rep.get("cad"), stock=rep.get("stock"), allowance_mm=_number(rep.get("allowance_mm")),
                      bounds_mm=bounds)
