"""Plain NumPy/float quaternion helpers for the flight software's hot path.

Scalar-first unit quaternions ``q = (w, x, y, z)``, the convention of
``scipy.spatial.transform.Rotation.from_quat(q, scalar_first=True)``:
``q_LB`` rotates body vectors into L. Each helper gives what the scipy
expression named in its docstring gives (tested against scipy on random
inputs, signs included), without building ``Rotation`` objects, which cost
tens of microseconds apiece on every control tick.
"""

from __future__ import annotations

import math

import numpy as np

from gnc.numeric import norm


def quat_normalize(q: np.ndarray) -> np.ndarray:
    """``q / |q|``, (4,)."""
    w, x, y, z = (float(c) for c in q)
    n = math.sqrt(w * w + x * x + y * y + z * z)
    return np.array([w / n, x / n, y / n, z / n])


def unit_quaternion(q: np.ndarray) -> np.ndarray | None:
    """The normalised quaternion, (4,), or None when it is non-finite, zero or not a 4-vector."""
    q = np.asarray(q, float)
    if q.shape != (4,):
        return None
    w, x, y, z = q.tolist()
    if not (math.isfinite(w) and math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
        return None
    scale = max(abs(w), abs(x), abs(y), abs(z))
    if scale == 0.0:
        return None
    q = q / scale
    return q / norm(q)


def body_z_L(q: np.ndarray) -> np.ndarray:
    """Body +z in L of a unit ``q_LB``, (3,): ``Rotation.from_quat(q, scalar_first=True).apply([0, 0, 1])``."""
    w, x, y, z = q.tolist()
    return np.array([2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)])


def quat_multiply(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product ``p q``, (4,): ``(Rotation(p) * Rotation(q)).as_quat(scalar_first=True)`` for unit p, q."""
    pw, px, py, pz = (float(c) for c in p)
    qw, qx, qy, qz = (float(c) for c in q)
    return np.array([
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    ])


def quat_conjugate(q: np.ndarray) -> np.ndarray:
    """``(w, -x, -y, -z)``, (4,): ``Rotation(q).inv().as_quat(scalar_first=True)`` for a unit q."""
    return np.array([float(q[0]), -float(q[1]), -float(q[2]), -float(q[3])])


def quat_error(q_cmd: np.ndarray, q: np.ndarray) -> np.ndarray:
    """``q_cmd^-1 q`` of the normalised inputs, (4,).

    ``(Rotation.from_quat(q_cmd, scalar_first=True).inv() * Rotation.from_quat(q, scalar_first=True))
    .as_quat(scalar_first=True)``.
    """
    return quat_multiply(quat_conjugate(quat_normalize(q_cmd)), quat_normalize(q))


def quat_from_matrix(R: np.ndarray) -> np.ndarray:
    """Scalar-first quaternion of a rotation matrix, (4,).

    ``Rotation.from_matrix(R).as_quat(scalar_first=True)`` for an orthonormal
    ``R`` with determinant +1: the same branch choice (Shepperd's method on the
    largest of the diagonal and the trace) and so the same sign.
    """
    r00, r01, r02 = float(R[0, 0]), float(R[0, 1]), float(R[0, 2])
    r10, r11, r12 = float(R[1, 0]), float(R[1, 1]), float(R[1, 2])
    r20, r21, r22 = float(R[2, 0]), float(R[2, 1]), float(R[2, 2])
    return quat_from_elements(r00, r01, r02, r10, r11, r12, r20, r21, r22)


def quat_from_elements(r00: float, r01: float, r02: float, r10: float, r11: float, r12: float,
                       r20: float, r21: float, r22: float) -> np.ndarray:
    """:func:`quat_from_matrix` of the matrix given by its elements ``r<row><column>`` as floats, (4,)."""
    trace = r00 + r11 + r22
    decision = (r00, r11, r22, trace)
    choice = max(range(4), key=decision.__getitem__)  # first of the largest, as numpy's argmax
    if choice == 0:
        x, y, z, w = 1.0 - trace + 2.0 * r00, r10 + r01, r20 + r02, r21 - r12
    elif choice == 1:
        x, y, z, w = r10 + r01, 1.0 - trace + 2.0 * r11, r21 + r12, r02 - r20
    elif choice == 2:
        x, y, z, w = r20 + r02, r21 + r12, 1.0 - trace + 2.0 * r22, r10 - r01
    else:
        x, y, z, w = r21 - r12, r02 - r20, r10 - r01, 1.0 + trace
    n = math.sqrt(w * w + x * x + y * y + z * z)
    return np.array([w / n, x / n, y / n, z / n])
