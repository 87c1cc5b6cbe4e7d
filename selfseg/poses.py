"""Rigid poses: 4×4 float64 ``T_a_b`` in metres mapping points from frame b into frame a, and BOP
records of them (rotation as 9 row-major floats, translation in millimetres)."""
from __future__ import annotations

from typing import Any

import numpy as np


def rt_to_T(R9: Any, t_mm: Any) -> np.ndarray:
    """BOP rotation (9, row-major) and translation (mm) → 4×4 pose in metres."""
    T = np.eye(4)
    T[:3, :3] = np.asarray(R9, dtype=np.float64).reshape(3, 3)
    T[:3, 3] = np.asarray(t_mm, dtype=np.float64).reshape(3) / 1000.0
    return T


def T_to_rt(T: np.ndarray) -> tuple[list[float], list[float]]:
    """4×4 pose in metres → BOP (R as 9 floats, t as 3 floats in mm)."""
    T = np.asarray(T, dtype=np.float64)
    return T[:3, :3].reshape(-1).tolist(), (T[:3, 3] * 1000.0).tolist()


def transform_points(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    """Apply a 4×4 rigid transform ``T_a_b`` to N×3 points in frame b; returns them in frame a (float64)."""
    T = np.asarray(T, dtype=np.float64)
    return np.asarray(points) @ T[:3, :3].T + T[:3, 3]


def invert_T(T: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4×4 transform."""
    Ti = np.eye(4)
    R = T[:3, :3]
    Ti[:3, :3] = R.T
    Ti[:3, 3] = -R.T @ T[:3, 3]
    return Ti
