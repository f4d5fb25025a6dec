"""Rotations, poses, camera models and homogeneous 2D helpers; no I/O.

Conventions (the same as COLMAP's, stated once here):

- World frame: x east, y north, z up, metres. The package works in a LOCAL
  frame, ``world_abs = local + origin`` (see :mod:`obliq_colmap.colmap_io`).
- ``cam_from_world`` maps a world point into the camera frame:
  ``X_cam = R @ X_world + t``; camera axes x right, y down, z forward.
- Pixel convention: the centre of the top-left pixel is at (0.5, 0.5), so a
  pixel with integer array indices (row, col) has its centre at
  ``(col + 0.5, row + 0.5)``.
- Camera models and their parameter order follow COLMAP
  (``pycolmap.Camera.params``); :func:`img_from_cam` reproduces
  ``pycolmap.Camera.img_from_cam`` for the models in :data:`SUPPORTED_MODELS`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

#: Camera models implemented in numpy here, with their parameter names.
SUPPORTED_MODELS: dict[str, tuple[str, ...]] = {
    "SIMPLE_PINHOLE": ("f", "cx", "cy"),
    "PINHOLE": ("fx", "fy", "cx", "cy"),
    "SIMPLE_RADIAL": ("f", "cx", "cy", "k"),
    "RADIAL": ("f", "cx", "cy", "k1", "k2"),
    "OPENCV": ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2"),
}

#: Offset from an array index to the COLMAP pixel coordinate of its centre.
PIXEL_CENTER_OFFSET = 0.5


# --------------------------------------------------------------------------
# Rotations and poses
# --------------------------------------------------------------------------


def rotation_z(alpha: float | np.ndarray) -> np.ndarray:
    """Rotation(s) about the world z axis by ``alpha`` radians.

    Parameters
    ----------
    alpha : float or (N,) array

    Returns
    -------
    (3, 3) or (N, 3, 3) array
    """
    a = np.asarray(alpha, dtype=float)
    c, s = np.cos(a), np.sin(a)
    z, o = np.zeros_like(a), np.ones_like(a)
    R = np.stack(
        [np.stack([c, -s, z], -1), np.stack([s, c, z], -1), np.stack([z, z, o], -1)],
        -2,
    )
    return R


def rotation_exp(omega: np.ndarray) -> np.ndarray:
    """Rodrigues' formula, vectorised: (..., 3) rotation vectors (axis * angle,
    radians) to (..., 3, 3) rotations."""
    omega = np.asarray(omega, float)
    theta = np.linalg.norm(omega, axis=-1)[..., None, None]
    K = skew(omega)
    small = theta < 1e-8
    t = np.where(small, 1.0, theta)
    # Series near zero: sin(t) / t and (1 - cos(t)) / t^2 lose all digits there.
    a = np.where(small, 1.0 - theta**2 / 6.0, np.sin(t) / t)
    b = np.where(small, 0.5 - theta**2 / 24.0, (1.0 - np.cos(t)) / t**2)
    return np.eye(3) + a * K + b * (K @ K)


def rotation_from_axis_angle(rotvec: np.ndarray) -> np.ndarray:
    """Rodrigues' formula: (3,) axis * angle (radians) to a (3, 3) rotation
    (:func:`rotation_exp` of one vector)."""
    return rotation_exp(np.asarray(rotvec, dtype=float)[None])[0]


def axis_angle_from_rotation(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation to its (3,) axis * angle (radians), the inverse of
    :func:`rotation_from_axis_angle` (angles up to pi)."""
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(np.asarray(R, dtype=float)).as_rotvec()


def skew(v: np.ndarray) -> np.ndarray:
    """(..., 3) vectors to their (..., 3, 3) cross-product matrices."""
    v = np.asarray(v, dtype=float)
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2] = -v[..., 2], v[..., 1]
    S[..., 1, 0], S[..., 1, 2] = v[..., 2], -v[..., 0]
    S[..., 2, 0], S[..., 2, 1] = -v[..., 1], v[..., 0]
    return S


def cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product over the last axis (np.cross has a large call overhead)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], -1)


_EYE3 = np.eye(3)


def tangent_basis(v: np.ndarray) -> np.ndarray:
    """(..., 3, 2) orthonormal bases of the planes perpendicular to unit v (..., 3):
    ``u1 = v x e`` for the axis ``e`` of v's smallest |component|, ``u2 = v x u1``.

    Smooth in v within each of three regions (chosen by v's smallest |component|);
    the quantities computed from it do not depend on the choice of basis.
    """
    v = np.asarray(v, float)
    if v.ndim == 1:
        return _tangent_basis_1(v)
    e = _EYE3[np.argmin(np.abs(v), axis=-1)]
    u1 = cross(v, e)
    u1 /= np.linalg.norm(u1, axis=-1, keepdims=True)
    return np.stack([u1, cross(v, u1)], axis=-1)


def _tangent_basis_1(v: np.ndarray) -> np.ndarray:
    """:func:`tangent_basis` of one (3,) vector in scalar arithmetic.

    Called thousands of times per image on single VPs, where numpy's per-call
    overhead is most of the cost.
    """
    x, y, z = float(v[0]), float(v[1]), float(v[2])
    ax, ay, az = abs(x), abs(y), abs(z)
    # v x e_k for the axis k of the smallest |component| (first on ties).
    if ax <= ay and ax <= az:
        a, b, c = 0.0, z, -y
    elif ay <= az:
        a, b, c = -z, 0.0, x
    else:
        a, b, c = y, -x, 0.0
    n = math.sqrt(a * a + b * b + c * c)
    a, b, c = a / n, b / n, c / n
    return np.array([[a, y * c - z * b], [b, z * a - x * c], [c, x * b - y * a]])


def rotation_aligning(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The smallest rotation R with ``R @ a`` parallel to ``b`` (both (3,))."""
    a = np.asarray(a, float) / np.linalg.norm(a)
    b = np.asarray(b, float) / np.linalg.norm(b)
    v = np.cross(a, b)
    s, c = np.linalg.norm(v), float(a @ b)
    if s < 1e-12:
        if c > 0:
            return np.eye(3)
        # Antiparallel: rotate by pi about any axis perpendicular to a.
        axis = np.cross(a, [1.0, 0.0, 0.0])
        if np.linalg.norm(axis) < 1e-6:
            axis = np.cross(a, [0.0, 1.0, 0.0])
        return rotation_from_axis_angle(np.pi * axis / np.linalg.norm(axis))
    return rotation_from_axis_angle(v / s * np.arctan2(s, c))


def quat_xyzw_from_rotation(R: np.ndarray) -> np.ndarray:
    """(3, 3) rotation to a unit quaternion [x, y, z, w] with w >= 0."""
    R = np.asarray(R, float)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * np.sqrt(tr + 1.0)
        q = [
            (R[2, 1] - R[1, 2]) / s,
            (R[0, 2] - R[2, 0]) / s,
            (R[1, 0] - R[0, 1]) / s,
            0.25 * s,
        ]
    else:
        i = int(np.argmax(np.diag(R)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * np.sqrt(1.0 + R[i, i] - R[j, j] - R[k, k])
        q = [0.0, 0.0, 0.0, (R[k, j] - R[j, k]) / s]
        q[i] = 0.25 * s
        q[j] = (R[j, i] + R[i, j]) / s
        q[k] = (R[k, i] + R[i, k]) / s
    q = np.asarray(q)
    q /= np.linalg.norm(q)
    return q if q[3] >= 0 else -q


def rotation_from_quat_xyzw(q: np.ndarray) -> np.ndarray:
    """Unit quaternion [x, y, z, w] to a (3, 3) rotation."""
    x, y, z, w = np.asarray(q, float) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def rotation_angle_deg(R_a: np.ndarray, R_b: np.ndarray) -> np.ndarray | float:
    """Angle in degrees of the relative rotation(s) ``R_a @ R_b.T``.

    ``arctan2(|sin|, cos)`` of the relative rotation rather than ``arccos`` of
    its trace, which keeps full precision for small angles: identical
    rotations give exactly 0 and 1e-6 deg is still resolved.

    Parameters
    ----------
    R_a, R_b : (3, 3) or (N, 3, 3) arrays of rotations.

    Returns
    -------
    float or (N,) array, degrees in [0, 180].
    """
    R_rel = np.asarray(R_a, float) @ np.swapaxes(np.asarray(R_b, float), -1, -2)
    cos = (np.trace(R_rel, axis1=-2, axis2=-1) - 1.0) / 2.0
    # The skew-symmetric part of R_rel is sin(angle) [axis]_x.
    w = np.stack(
        [
            R_rel[..., 2, 1] - R_rel[..., 1, 2],
            R_rel[..., 0, 2] - R_rel[..., 2, 0],
            R_rel[..., 1, 0] - R_rel[..., 0, 1],
        ],
        axis=-1,
    )
    sin = np.linalg.norm(w, axis=-1) / 2.0
    angle = np.degrees(np.arctan2(sin, cos))
    return float(angle) if angle.ndim == 0 else angle


@dataclass
class Pose:
    """A rigid ``cam_from_world`` transform: ``X_cam = rotation @ X + translation``.

    Attributes
    ----------
    rotation : (3, 3) float array, orthonormal with det +1.
    translation : (3,) float array, metres.
    """

    rotation: np.ndarray = field(default_factory=lambda: np.eye(3))
    translation: np.ndarray = field(default_factory=lambda: np.zeros(3))

    def __post_init__(self) -> None:
        self.rotation = np.asarray(self.rotation, dtype=float).reshape(3, 3)
        self.translation = np.asarray(self.translation, dtype=float).reshape(3)

    @classmethod
    def from_center(cls, rotation: np.ndarray, center: np.ndarray) -> Pose:
        """Pose from a rotation and a camera centre in world coordinates."""
        R = np.asarray(rotation, float)
        return cls(R, -R @ np.asarray(center, float))

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates."""
        return -self.rotation.T @ self.translation

    def inverse(self) -> Pose:
        """The ``world_from_cam`` transform."""
        return Pose(self.rotation.T, self.center)

    def transform(self, points_world: np.ndarray) -> np.ndarray:
        """(N, 3) world points to (N, 3) camera-frame points."""
        return np.asarray(points_world, float) @ self.rotation.T + self.translation

    def matrix(self) -> np.ndarray:
        """(3, 4) matrix [R | t]."""
        return np.hstack([self.rotation, self.translation[:, None]])

    def to_rigid3d(self):
        """As a ``pycolmap.Rigid3d``."""
        import pycolmap

        q = quat_xyzw_from_rotation(self.rotation)
        return pycolmap.Rigid3d(pycolmap.Rotation3d(q), self.translation.copy())

    @classmethod
    def from_rigid3d(cls, rigid) -> Pose:
        """From a ``pycolmap.Rigid3d`` (``cam_from_world``)."""
        m = np.asarray(rigid.matrix())
        return cls(m[:, :3], m[:, 3])


# --------------------------------------------------------------------------
# Camera models (COLMAP's, vectorised)
# --------------------------------------------------------------------------


def _split_params(model: str, params: np.ndarray):
    """(fx, fy, cx, cy, k1, k2, p1, p2) of any supported model."""
    p = np.asarray(params, float)
    if model not in SUPPORTED_MODELS:
        raise ValueError(
            f"camera model {model!r} is not supported; "
            f"supported: {', '.join(SUPPORTED_MODELS)}"
        )
    if p.shape != (len(SUPPORTED_MODELS[model]),):
        raise ValueError(
            f"{model} takes {len(SUPPORTED_MODELS[model])} params "
            f"{SUPPORTED_MODELS[model]}, got shape {p.shape}"
        )
    k1 = k2 = p1 = p2 = 0.0
    if model == "SIMPLE_PINHOLE":
        f, cx, cy = p
        fx = fy = f
    elif model == "PINHOLE":
        fx, fy, cx, cy = p
    elif model == "SIMPLE_RADIAL":
        f, cx, cy, k1 = p
        fx = fy = f
    elif model == "RADIAL":
        f, cx, cy, k1, k2 = p
        fx = fy = f
    else:  # OPENCV
        fx, fy, cx, cy, k1, k2, p1, p2 = p
    return fx, fy, cx, cy, k1, k2, p1, p2


def distortion(model: str, params: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """COLMAP's distortion offset (du, dv) at normalised coordinates.

    Parameters
    ----------
    uv : (N, 2) array of normalised (undistorted) image coordinates x/z, y/z.

    Returns
    -------
    (N, 2) array; the distorted coordinate is ``uv + distortion(...)``.
    """
    _, _, _, _, k1, k2, p1, p2 = _split_params(model, params)
    u, v = uv[:, 0], uv[:, 1]
    u2, v2, uv_ = u * u, v * v, u * v
    r2 = u2 + v2
    radial = k1 * r2 + k2 * r2 * r2
    du = u * radial + 2.0 * p1 * uv_ + p2 * (r2 + 2.0 * u2)
    dv = v * radial + 2.0 * p2 * uv_ + p1 * (r2 + 2.0 * v2)
    return np.stack([du, dv], axis=1)


def calibration_matrix(model: str, params: np.ndarray) -> np.ndarray:
    """(3, 3) K of the model's pinhole part (distortion ignored)."""
    fx, fy, cx, cy, *_ = _split_params(model, params)
    return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def img_from_cam(model: str, params: np.ndarray, points_cam: np.ndarray) -> np.ndarray:
    """Project camera-frame points to pixels, as ``pycolmap.Camera.img_from_cam``.

    Parameters
    ----------
    points_cam : (N, 3) array, camera frame. Points with z <= 0 give NaN.

    Returns
    -------
    (N, 2) array of pixel coordinates (COLMAP convention).
    """
    fx, fy, cx, cy, *_ = _split_params(model, params)
    X = np.asarray(points_cam, float).reshape(-1, 3)
    z = X[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        uv = X[:, :2] / np.where(z > 0, z, np.nan)[:, None]
    uv = uv + distortion(model, params, uv)
    return np.stack([fx * uv[:, 0] + cx, fy * uv[:, 1] + cy], axis=1)


def cam_from_img(
    model: str, params: np.ndarray, pixels: np.ndarray, num_iterations: int = 20
) -> np.ndarray:
    """Pixels to normalised (undistorted) coordinates, inverting the distortion.

    Newton's method on all points at once with an analytic 2x2 Jacobian of the
    distortion; exact in one step for models without distortion.

    Parameters
    ----------
    pixels : (N, 2) array, COLMAP pixel convention.

    Returns
    -------
    (N, 2) array of normalised coordinates (x/z, y/z).
    """
    fx, fy, cx, cy, k1, k2, p1, p2 = _split_params(model, params)
    xy = np.asarray(pixels, float).reshape(-1, 2)
    target = np.stack([(xy[:, 0] - cx) / fx, (xy[:, 1] - cy) / fy], axis=1)
    if (k1 == 0.0 and k2 == 0.0 and p1 == 0.0 and p2 == 0.0) or not len(xy):
        return target
    uv = target.copy()
    for _ in range(num_iterations):
        u, v = uv[:, 0], uv[:, 1]
        r2 = u * u + v * v
        radial = k1 * r2 + k2 * r2 * r2
        dradial = k1 + 2.0 * k2 * r2  # d radial / d r2
        res = uv + distortion(model, params, uv) - target
        # Jacobian of uv + d(uv): J = I + d(d)/d(uv).
        j00 = 1 + radial + 2 * u * u * dradial + 2 * p1 * v + 6 * p2 * u
        j01 = 2 * u * v * dradial + 2 * p1 * u + 2 * p2 * v
        j10 = 2 * u * v * dradial + 2 * p2 * v + 2 * p1 * u
        j11 = 1 + radial + 2 * v * v * dradial + 2 * p2 * u + 6 * p1 * v
        det = j00 * j11 - j01 * j10
        step_u = (j11 * res[:, 0] - j01 * res[:, 1]) / det
        step_v = (-j10 * res[:, 0] + j00 * res[:, 1]) / det
        uv[:, 0] -= step_u
        uv[:, 1] -= step_v
        if np.nanmax(np.abs(res)) < 1e-14:
            break
    return uv


@dataclass
class Camera:
    """Intrinsics of one physical camera, COLMAP model and parameter order.

    Attributes
    ----------
    model : str, a key of :data:`SUPPORTED_MODELS`.
    width, height : int, pixels.
    params : (P,) float array in COLMAP's order for ``model``.
    camera_id : int, COLMAP camera id.
    """

    model: str
    width: int
    height: int
    params: np.ndarray
    camera_id: int = 1

    def __post_init__(self) -> None:
        self.params = np.asarray(self.params, dtype=float).copy()
        _split_params(self.model, self.params)  # validates

    @property
    def K(self) -> np.ndarray:
        """(3, 3) calibration matrix of the pinhole part."""
        return calibration_matrix(self.model, self.params)

    @property
    def has_distortion(self) -> bool:
        return any(_split_params(self.model, self.params)[4:])

    def img_from_cam(self, points_cam: np.ndarray) -> np.ndarray:
        """(N, 3) camera-frame points to (N, 2) pixels."""
        return img_from_cam(self.model, self.params, points_cam)

    def cam_from_img(self, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) pixels to (N, 2) normalised undistorted coordinates."""
        return cam_from_img(self.model, self.params, pixels)

    def undistort_pixels(self, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) pixels to (N, 2) pixels of the distortion-free pinhole ``K``."""
        uv = self.cam_from_img(pixels)
        return uv @ self.K[:2, :2].T + self.K[:2, 2]

    def distort_pixels(self, pixels: np.ndarray) -> np.ndarray:
        """(N, 2) pixels of the pinhole ``K`` to (N, 2) raw (distorted) pixels.

        The inverse of :meth:`undistort_pixels`.
        """
        px = np.asarray(pixels, float).reshape(-1, 2)
        uv = (px - self.K[:2, 2]) / np.diag(self.K)[:2]
        return self.img_from_cam(np.column_stack([uv, np.ones(len(uv))]))

    def with_focal_scaled(self, scale: float) -> Camera:
        """The camera with its focal length(s) multiplied by ``scale``."""
        params = np.array(self.params, float)
        nf = 2 if self.model in ("PINHOLE", "OPENCV") else 1
        params[:nf] *= scale
        return Camera(self.model, self.width, self.height, params, self.camera_id)

    def with_model(self, model: str) -> Camera:
        """The same camera expressed in another COLMAP model.

        Focal lengths, principal point and the distortion terms both models
        have are kept; a single focal is the mean of fx and fy; distortion
        terms the new model adds start at 0 (the bundle refines them) and
        terms it lacks are dropped (the caller is warned by the pipeline).
        """
        fx, fy, cx, cy, k1, k2, p1, p2 = _split_params(self.model, self.params)
        f = 0.5 * (fx + fy)
        params = {
            "SIMPLE_PINHOLE": [f, cx, cy],
            "PINHOLE": [fx, fy, cx, cy],
            "SIMPLE_RADIAL": [f, cx, cy, k1],
            "RADIAL": [f, cx, cy, k1, k2],
            "OPENCV": [fx, fy, cx, cy, k1, k2, p1, p2],
        }
        if model not in params:
            _split_params(model, np.zeros(0))  # raises the standard message
        return Camera(model, self.width, self.height, params[model], self.camera_id)

    def to_pycolmap(self):
        """As a ``pycolmap.Camera``."""
        import pycolmap

        return pycolmap.Camera(
            model=self.model,
            width=int(self.width),
            height=int(self.height),
            params=self.params.tolist(),
            camera_id=int(self.camera_id),
        )

    @classmethod
    def from_pycolmap(cls, camera) -> Camera:
        """From a ``pycolmap.Camera``; raises ValueError for unsupported models."""
        name = camera.model.name if hasattr(camera.model, "name") else str(camera.model)
        return cls(
            model=name,
            width=int(camera.width),
            height=int(camera.height),
            params=np.asarray(camera.params, float),
            camera_id=int(camera.camera_id),
        )


def vertical_vp_in_frame(camera: Camera, down_cam: np.ndarray) -> np.ndarray | None:
    """The (2,) pixel of the vertical vanishing point of the world's down
    direction ``down_cam`` (3,) in the camera frame, when it lies inside the
    image (pinhole part): a nadir view. None otherwise."""
    v = camera.K @ np.asarray(down_cam, float)
    if v[2] <= 0:  # the nadir is behind the camera
        return None
    x, y = v[:2] / v[2]
    inside = 0.0 <= x <= camera.width and 0.0 <= y <= camera.height
    return np.array([x, y]) if inside else None


def project(
    camera: Camera, pose: Pose, points_world: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Project world points into an image.

    Parameters
    ----------
    points_world : (N, 3) array, metres (local frame).

    Returns
    -------
    pixels : (N, 2) array; NaN where the point is behind the camera.
    depth : (N,) array, camera-frame z in metres.
    """
    X = pose.transform(np.asarray(points_world, float).reshape(-1, 3))
    return camera.img_from_cam(X), X[:, 2]


# --------------------------------------------------------------------------
# Homogeneous 2D helpers
# --------------------------------------------------------------------------


def to_homogeneous(points: np.ndarray) -> np.ndarray:
    """(N, D) to (N, D + 1) by appending ones."""
    points = np.asarray(points, float)
    return np.concatenate([points, np.ones(points.shape[:-1] + (1,))], axis=-1)


def lines_through(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Homogeneous lines through point pairs, normalised so (a, b) is a unit normal.

    Parameters
    ----------
    p, q : (N, 2) arrays of pixel coordinates.

    Returns
    -------
    (N, 3) array of lines ``(a, b, c)`` with ``a x + b y + c = 0``.
    """
    lines = np.cross(to_homogeneous(p), to_homogeneous(q))
    return normalize_lines(lines)


def normalize_lines(lines: np.ndarray) -> np.ndarray:
    """Scale (N, 3) homogeneous lines so that a^2 + b^2 = 1."""
    lines = np.asarray(lines, float)
    n = np.linalg.norm(lines[..., :2], axis=-1, keepdims=True)
    return lines / np.where(n > 0, n, 1.0)


def point_line_distance(points: np.ndarray, lines: np.ndarray) -> np.ndarray:
    """Signed distances (N,) of (N, 2) points to (N, 3) lines (broadcasting)."""
    lines = normalize_lines(lines)
    points = np.asarray(points, float)
    return (
        points[..., 0] * lines[..., 0] + points[..., 1] * lines[..., 1] + lines[..., 2]
    )


def parabola_peak(x: np.ndarray, y: np.ndarray) -> float:
    """Abscissa of the vertex of the parabola through three equally spaced
    (x, y) (3,), within [x[0], x[2]]; x[1] when it is not concave (or a
    value is NaN)."""
    h = x[1] - x[0]
    curv = y[0] - 2.0 * y[1] + y[2]
    if not curv < 0:
        return float(x[1])
    return float(np.clip(x[1] + 0.5 * h * (y[0] - y[2]) / curv, x[0], x[2]))
