"""Write config/parts/square-hole.stl: the Fang 2019 test part, a 70 x 70 mm square with a centred
35 mm round hole, 30 mm tall. Run: .venv/bin/python config/parts/make_demo_part.py"""
from __future__ import annotations

from pathlib import Path

import trimesh
from shapely.geometry import Point, box

from planner.extrude import extrude


def square_hole(size: float = 70.0, hole_d: float = 35.0, height: float = 30.0) -> trimesh.Trimesh:
    section = box(-size / 2, -size / 2, size / 2, size / 2).difference(Point(0, 0).buffer(hole_d / 2, quad_segs=32))
    mesh = extrude(section, height)
    mesh.apply_translation([size / 2, size / 2, 0.0])  # corner at the origin, part in +x +y
    return mesh


if __name__ == "__main__":
    out = Path(__file__).with_name("square-hole.stl")
    out.write_bytes(square_hole().export(file_type="stl"))
    print(out)
