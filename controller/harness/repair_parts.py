"""The demo repair's parts (a block with a pocket milled into one corner, and its nominal CAD)
and a simulator config with the stock posed on the CNC table: `cell demo --repair`, tests, benches."""
from __future__ import annotations

from pathlib import Path

import trimesh

from controller.job.repair_volume import to_manifold, to_trimesh
from core.config import SimConfig, load_sim


def make_parts(tmp: Path) -> tuple[Path, Path]:
    cad = trimesh.creation.box(extents=(100, 100, 20))
    cad.apply_translation((0, 0, -10))
    pocket = trimesh.creation.box(extents=(20, 20, 4))
    pocket.apply_translation((40, 40, -2))
    stock = to_trimesh(to_manifold(cad, "cad") - to_manifold(pocket, "pocket"))
    cad.export(tmp / "cad.stl")
    stock.export(tmp / "stock.stl")
    return tmp / "cad.stl", tmp / "stock.stl"


def posed_sim(stock: Path, a: float, b: float, c: float, off: tuple[float, float, float]) -> SimConfig:
    sim = load_sim()
    wp = sim.cnc.workpiece.model_copy(update={"mesh": str(stock), "tilt_a_deg": a, "tilt_b_deg": b,
                                              "rotation_c_deg": c, "offset_mm": off})
    return sim.model_copy(update={"cnc": sim.cnc.model_copy(update={"workpiece": wp})})
