"""Parts for the 5-axis tests: a tube tilted 45° from vertical and a cone frustum with 45° walls."""
from __future__ import annotations

import numpy as np
import trimesh


def tilted_tube(r_out: float = 12.0, wall: float = 5.0, height: float = 4.0, tilt_deg: float = 45.0,
                sections: int = 96) -> trimesh.Trimesh:
    """An annulus swept along an axis tilted `tilt_deg` from vertical (toward +x): flat ends."""
    ring = trimesh.creation.annulus(r_min=r_out - wall, r_max=r_out, height=height, sections=sections)
    ring.apply_translation((0, 0, height / 2.0))
    shear = np.eye(4)
    shear[0, 2] = np.tan(np.radians(tilt_deg))  # x += z·tan(tilt): horizontal sections shift
    ring.apply_transform(shear)
    return ring


def cone_frustum(r0: float = 10.0, wall: float = 5.0, height: float = 4.0, wall_deg: float = 45.0,
                 sections: int = 96) -> trimesh.Trimesh:
    """A hollow frustum widening upward, its walls `wall_deg` from vertical."""
    d = height * np.tan(np.radians(wall_deg))
    profile = np.array([[r0, 0.0], [r0 + wall, 0.0], [r0 + wall + d, height], [r0 + d, height], [r0, 0.0]])
    return trimesh.creation.revolve(profile, sections=sections)
