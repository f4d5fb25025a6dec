"""Exterior orientation as omega, phi, kappa (Pix4D's convention).

Pix4D's camera axes are x right, y up, z back (the camera looks along -z);
``R = Rx(omega) Ry(phi) Rz(kappa)`` rotates camera axes into the map grid
(``X_map = R X_cam_pix4d + C``). COLMAP's camera has y down, z forward,
so ``cam_from_world = diag(1, -1, -1) R^T``. At omega = phi = kappa = 0 the
camera looks straight down with the image top towards grid north.
"""

from __future__ import annotations

import numpy as np

#: Pix4D camera axes (y up, z back) to COLMAP's (y down, z forward).
FLIP_YZ = np.diag([1.0, -1.0, -1.0])


def _rx(a: np.ndarray) -> np.ndarray:
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([o, z, z, z, c, -s, z, s, c], -1).reshape(*a.shape, 3, 3)


def _ry(a: np.ndarray) -> np.ndarray:
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([c, z, s, z, o, z, -s, z, c], -1).reshape(*a.shape, 3, 3)


def _rz(a: np.ndarray) -> np.ndarray:
    c, s, o, z = np.cos(a), np.sin(a), np.ones_like(a), np.zeros_like(a)
    return np.stack([c, -s, z, s, c, z, z, z, o], -1).reshape(*a.shape, 3, 3)


def cam_from_world_from_opk(opk_deg: np.ndarray) -> np.ndarray:
    """(N, 3) omega, phi, kappa in degrees -> (N, 3, 3) COLMAP cam_from_world."""
    a = np.radians(np.asarray(opk_deg, float).reshape(-1, 3))
    R = _rx(a[:, 0]) @ _ry(a[:, 1]) @ _rz(a[:, 2])
    return FLIP_YZ @ np.swapaxes(R, -1, -2)


def opk_from_cam_from_world(rotations: np.ndarray) -> np.ndarray:
    """(N, 3, 3) COLMAP cam_from_world -> (N, 3) omega, phi, kappa in degrees.

    From ``R = Rx Ry Rz``: ``R[0,2] = sin(phi)``, ``R[1,2] = -sin(omega)
    cos(phi)``, ``R[2,2] = cos(omega) cos(phi)``, ``R[0,1] = -cos(phi)
    sin(kappa)``, ``R[0,0] = cos(phi) cos(kappa)``; phi in [-90, 90].
    """
    Rc = np.asarray(rotations, float).reshape(-1, 3, 3)
    R = np.swapaxes(Rc, -1, -2) @ FLIP_YZ  # (FLIP R^T)^T = R FLIP, FLIP = FLIP^T
    omega = np.arctan2(-R[:, 1, 2], R[:, 2, 2])
    phi = np.arcsin(np.clip(R[:, 0, 2], -1.0, 1.0))
    kappa = np.arctan2(-R[:, 0, 1], R[:, 0, 0])
    return np.degrees(np.column_stack([omega, phi, kappa]))
