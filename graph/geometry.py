"""SE(3) helpers: 4x4 homogeneous poses, TUM quaternions, relative motion magnitudes."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def pose_from_tum(values: np.ndarray) -> np.ndarray:
    """4x4 pose from a TUM row ``tx ty tz qx qy qz qw`` (Hamilton, scalar last)."""
    values = np.asarray(values, dtype=float)
    T = np.eye(4)
    T[:3, :3] = Rotation.from_quat(values[3:7]).as_matrix()
    T[:3, 3] = values[:3]
    return T


def pose_to_tum(T: np.ndarray) -> np.ndarray:
    """TUM row ``tx ty tz qx qy qz qw`` from a 4x4 pose (qw >= 0)."""
    q = Rotation.from_matrix(T[:3, :3]).as_quat()
    if q[3] < 0:
        q = -q
    return np.concatenate([T[:3, 3], q])


def inverse(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid transform."""
    Ti = np.eye(4)
    R = T[:3, :3]
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti


def relative(T_a: np.ndarray, T_b: np.ndarray) -> np.ndarray:
    """Pose of b in the frame of a: ``T_a^-1 T_b``."""
    return inverse(T_a) @ T_b


def rotation_angle(R: np.ndarray) -> float:
    """Angle in radians of a rotation matrix, ``||log(R)||``."""
    c = (np.trace(R) - 1.0) / 2.0
    return float(np.arccos(np.clip(c, -1.0, 1.0)))


def motion_magnitude(T_rel: np.ndarray) -> tuple[float, float]:
    """Translation (m) and rotation angle (rad) of a relative pose (eq. 2.16's tau and phi)."""
    return float(np.linalg.norm(T_rel[:3, 3])), rotation_angle(T_rel[:3, :3])


def disagreements(T_a: np.ndarray, T_b: np.ndarray, T_ab: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``motion_magnitude(relative(relative(T_a, T_b), T_ab))`` of many (n, 4, 4) stacks at once: how far each
    measured ``T_ab`` is from the relative pose of ``T_a`` and ``T_b``, in m and rad."""
    Ra, Rb, Rm = T_a[:, :3, :3], T_b[:, :3, :3], T_ab[:, :3, :3]
    R = np.swapaxes(Ra, 1, 2) @ Rb  # the estimate T_a^-1 T_b
    t = np.einsum("nji,nj->ni", Ra, T_b[:, :3, 3] - T_a[:, :3, 3])
    Re = np.swapaxes(R, 1, 2) @ Rm  # its inverse times the measurement
    te = np.einsum("nji,nj->ni", R, T_ab[:, :3, 3] - t)
    c = (np.trace(Re, axis1=1, axis2=2) - 1.0) / 2.0
    return np.linalg.norm(te, axis=1), np.arccos(np.clip(c, -1.0, 1.0))


def is_rigid(T: np.ndarray, tol: float = 1e-3) -> bool:
    """True when T is a finite 4x4 rigid transform (orthonormal rotation, det +1, last row 0 0 0 1)."""
    T = np.asarray(T)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        return False
    R = T[:3, :3]
    return bool(
        np.allclose(R @ R.T, np.eye(3), atol=tol)
        and abs(np.linalg.det(R) - 1.0) < tol
        and np.allclose(T[3], [0, 0, 0, 1], atol=tol)
    )


def rotation_angles_between(Ra: np.ndarray, Rb: np.ndarray) -> np.ndarray:
    """Angles in radians between rotation pairs (N, 3, 3): ``||log(Ra_i^T Rb_i)||`` for each i, batched."""
    c = (np.einsum("nij,nij->n", Ra, Rb) - 1.0) / 2.0
    return np.arccos(np.clip(c, -1.0, 1.0))
