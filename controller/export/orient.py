"""Tool orientations for robot programs: a tool axis (part frame, +Z = vertical torch) as the
robot's tool frame, in ABB's quaternion and KUKA's A/B/C (Z-Y'-X'' Euler, degrees) conventions.

The job's tool axis points from the tool tip back to the torch. ABB's tool frame has its z axis
out of the torch toward the work, KUKA's its x axis; both are the opposite of the job's axis.
The free rotation about the axis is fixed by keeping the tool's other axis in the plane of
world X (or world Y when the axis is along X), so the wrist does not turn along a bead.
"""
from __future__ import annotations

import warnings

import numpy as np
from scipy.spatial.transform import Rotation


def _frame(approach: np.ndarray) -> np.ndarray:
    """Columns (x, y, z) of a right-handed frame whose z is `approach`."""
    z = approach / np.linalg.norm(approach)
    ref = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = ref - z * float(ref @ z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return np.column_stack([x, y, z])


def abb_quaternion(tool_axis: np.ndarray) -> np.ndarray:
    """[q1, q2, q3, q4] = [w, x, y, z] with the tool's z toward the work (−tool_axis)."""
    qx, qy, qz, qw = Rotation.from_matrix(_frame(-np.asarray(tool_axis, float))).as_quat()
    q = np.array([qw, qx, qy, qz])
    return -q if q[0] < 0 else q


def abb_tool_axis(q: np.ndarray) -> np.ndarray:
    """The job's tool axis back from an ABB quaternion."""
    w, x, y, z = q
    return -np.asarray(Rotation.from_quat([x, y, z, w]).as_matrix(), dtype=float)[:, 2]


def kuka_abc(tool_axis: np.ndarray) -> np.ndarray:
    """KUKA A, B, C (degrees, rotations about Z, Y', X'') with the tool's x toward the work."""
    f = _frame(-np.asarray(tool_axis, float))
    m = np.column_stack([f[:, 2], f[:, 0], f[:, 1]])  # tool x = approach, y, z complete the frame
    with warnings.catch_warnings():  # a vertical torch is gimbal lock (B = ±90°): any A−C split is right
        warnings.simplefilter("ignore", UserWarning)
        return np.asarray(Rotation.from_matrix(m).as_euler("ZYX", degrees=True), dtype=float)


def kuka_tool_axis(abc: np.ndarray) -> np.ndarray:
    """The job's tool axis back from KUKA A, B, C."""
    return -np.asarray(Rotation.from_euler("ZYX", abc, degrees=True).as_matrix(), dtype=float)[:, 0]


def rigid_quaternion(m: np.ndarray) -> np.ndarray:
    """[w, x, y, z] of a 4×4 rigid transform's rotation."""
    qx, qy, qz, qw = Rotation.from_matrix(m[:3, :3]).as_quat()
    q = np.array([qw, qx, qy, qz])
    return -q if q[0] < 0 else q
