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


def leaning_frustum(r: float = 30.0, wall: float = 5.0, height: float = 10.0, flare_deg: float = 0.0,
                    lean_deg: float = 32.0, sections: int = 96) -> tuple[trimesh.Trimesh, np.ndarray]:
    """A hollow frustum (a tube at `flare_deg` 0) turned `lean_deg` about y, cut by the planes
    z = 0 and z = `height`: flat ends, every layer a full ring. Its walls flare `flare_deg` from
    its own axis (outward when positive). `r` is the outer radius on the bottom plane's local ring.

    Returns the mesh and its 3×3 rotation R (local frame → part): the local wall generator through
    an angle φ, (tan(flare)·cos φ, tan(flare)·sin φ, 1), turned by R is the build direction there."""
    b = np.radians(lean_deg)
    R = np.array([[np.cos(b), 0.0, np.sin(b)], [0.0, 1.0, 0.0], [-np.sin(b), 0.0, np.cos(b)]])
    phi = np.linspace(0.0, 2.0 * np.pi, sections, endpoint=False)
    cs = np.column_stack([np.cos(phi), np.sin(phi), np.zeros(sections)])
    gen = (cs * np.tan(np.radians(flare_deg)) + [0.0, 0.0, 1.0]) @ R.T
    rings = []
    for radius in (r, r - wall):
        base = (cs * radius) @ R.T + [0.0, 0.0, height]  # the local ring sits inside the slab
        for z in (0.0, height):  # slide along the generator onto the plane
            s = (z - base[:, 2]) / gen[:, 2]
            rings.append(base + s[:, None] * gen)
    v = np.vstack(rings)  # outer bottom, outer top, inner bottom, inner top
    ob, ot, ib, it = (np.arange(sections) + k * sections for k in range(4))
    nx = np.roll(np.arange(sections), -1)
    faces = []
    for lo, hi, flip in ((ob, ot, False), (ib, it, True), (ib, ob, False), (ot, it, False)):
        q = np.column_stack([lo, lo[nx], hi[nx], hi])
        tri = np.vstack([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
        faces.append(tri[:, ::-1] if flip else tri)
    mesh = trimesh.Trimesh(v, np.vstack(faces), process=True)
    mesh.fix_normals()
    return mesh, R
