"""2D line segments: detection, edge points, segment utilities.

Stage 1a of the pipeline (Habbecke & Kobbelt, section 2.1; MetropoGIS,
section 3.1). :func:`detect_segments` turns a grayscale image into straight
segments with sub-pixel endpoints, the side that is brighter and the edge
strength. It uses OpenCV's LSD (Grompone von Gioi et al.) where the installed
OpenCV has it, and otherwise a Canny-style detector: sub-pixel edge points
(non-maximum suppression along the gradient, hysteresis), grouping into
line-support regions of similar orientation, least-squares line fits and
collinear merging, in the spirit of MetropoGIS.

The same edge-point machinery (:func:`edge_points`) serves the second pass of
:mod:`obliq_colmap.vanishing`, where the derivative is taken perpendicular to
the line from the vanishing point instead of along the gradient.

Coordinates are COLMAP pixels (:mod:`obliq_colmap.geometry`): the centre of the
top-left pixel is at (0.5, 0.5). OpenCV's LSD reports pixel centres at integers
and, with its internal Gaussian sub-sampling by ``scale``, at
``x_colmap - 0.5 / scale``; :func:`detect_segments` corrects both. Because the
convention puts the pixel *edges* at integers, a resized image maps to the
original by a pure scale, which is how detection at reduced resolution is
brought back to full resolution.
"""

from __future__ import annotations

import functools
import logging
from dataclasses import dataclass, field

import cv2
import numpy as np

from obliq_colmap.geometry import PIXEL_CENTER_OFFSET, Camera

logger = logging.getLogger(__name__)

DETECTORS = ("auto", "lsd", "canny")


# --------------------------------------------------------------------------
# Segments
# --------------------------------------------------------------------------


@dataclass
class Segments:
    """A set of 2D line segments.

    Attributes
    ----------
    endpoints : (N, 2, 2) float array
        ``endpoints[i, k]`` is endpoint k (x, y) of segment i, COLMAP pixels.
    normal : (N, 2) float array
        Unit normal of each segment pointing to its brighter side.
    strength : (N,) float array
        Mean gradient magnitude across the segment, grey levels per pixel
        (0-255 images), measured at the resolution of detection.
    pixel_scale : float
        Pixels of ``endpoints`` per pixel of the image the segments were
        detected in (``max(W, H) / LineOptions.max_image_size_px`` for a big
        image, else 1). The endpoints' localisation noise is about constant in
        detection pixels, so tolerances on these segments scale with it.
    """

    endpoints: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    normal: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    strength: np.ndarray = field(default_factory=lambda: np.zeros(0))
    pixel_scale: float = 1.0

    def __post_init__(self) -> None:
        self.endpoints = np.asarray(self.endpoints, float).reshape(-1, 2, 2)
        n = len(self.endpoints)
        self.normal = np.asarray(self.normal, float).reshape(n, 2)
        self.strength = np.asarray(self.strength, float).reshape(n)

    def __len__(self) -> int:
        return len(self.endpoints)

    @property
    def lengths(self) -> np.ndarray:
        """(N,) segment lengths, pixels."""
        return np.linalg.norm(self.endpoints[:, 1] - self.endpoints[:, 0], axis=1)

    @property
    def midpoints(self) -> np.ndarray:
        """(N, 2) segment midpoints, pixels."""
        return self.endpoints.mean(axis=1)

    @property
    def directions(self) -> np.ndarray:
        """(N, 2) unit directions from endpoint 0 to endpoint 1."""
        d = self.endpoints[:, 1] - self.endpoints[:, 0]
        n = np.linalg.norm(d, axis=1, keepdims=True)
        return d / np.where(n > 0, n, 1.0)

    def lines(self) -> np.ndarray:
        """(N, 3) homogeneous lines through the segments, unit normal (a, b)."""
        from obliq_colmap.geometry import lines_through

        return lines_through(self.endpoints[:, 0], self.endpoints[:, 1])

    def subset(self, index: np.ndarray) -> Segments:
        """The segments selected by a boolean mask or an index array."""
        return Segments(
            self.endpoints[index],
            self.normal[index],
            self.strength[index],
            self.pixel_scale,
        )

    def scaled(self, factor: float) -> Segments:
        """Coordinates multiplied by ``factor`` (a resize in COLMAP pixels)."""
        return Segments(
            self.endpoints * factor,
            self.normal.copy(),
            self.strength.copy(),
            self.pixel_scale * factor,
        )

    def undistorted(self, camera: Camera | None) -> Segments:
        """Endpoints mapped to the distortion-free pinhole image of ``camera``.

        Straight scene lines are straight only there. Returns ``self`` when the
        camera is None or has no distortion.
        """
        if camera is None or not camera.has_distortion or len(self) == 0:
            return self
        xy = camera.undistort_pixels(self.endpoints.reshape(-1, 2))
        out = Segments(
            xy.reshape(-1, 2, 2),
            self.normal.copy(),
            self.strength.copy(),
            self.pixel_scale,
        )
        # The bright side keeps its side of the (slightly rotated) segment.
        d = out.directions
        left = np.stack([d[:, 1], -d[:, 0]], axis=1)
        sign = np.sign(np.sum(left * self.normal, axis=1))
        out.normal = left * np.where(sign == 0, 1.0, sign)[:, None]
        return out

    @classmethod
    def concatenate(cls, parts: list[Segments]) -> Segments:
        """All segments of ``parts`` in one set (the coarsest ``pixel_scale``)."""
        if not parts:
            return cls()
        return cls(
            np.concatenate([p.endpoints for p in parts]),
            np.concatenate([p.normal for p in parts]),
            np.concatenate([p.strength for p in parts]),
            max(p.pixel_scale for p in parts),
        )


# --------------------------------------------------------------------------
# Options
# --------------------------------------------------------------------------


@dataclass(kw_only=True)
class LineOptions:
    """Options of :func:`detect_segments`."""

    #: "lsd" (OpenCV's LSD), "canny" (Canny-style fallback) or "auto" (LSD
    #: where the installed OpenCV has it, else Canny).
    detector: str = "auto"
    #: detect on a copy downsampled so that its longer side is at most this
    #: many pixels (INTER_AREA); None or 0 detects at full resolution.
    #: Segments are always returned in full-resolution pixels.
    max_image_size_px: int | None = 2048
    #: LSD's internal Gaussian sub-sampling factor (OpenCV's default 0.8).
    lsd_scale: float = 0.8
    #: LSD's standard refinement (splits segments at curvature); off by default
    #: because it costs ~20% time and the vanishing stage merges anyway.
    lsd_refine: bool = False
    #: shortest segment kept, pixels of the detection image.
    min_length_px: float = 8.0
    #: Canny fallback: Gaussian smoothing before the gradient, pixels.
    canny_sigma_px: float = 1.0
    #: Canny fallback: hysteresis thresholds on the gradient, grey levels/px.
    canny_low: float = 4.0
    canny_high: float = 12.0
    #: Canny fallback: largest RMS distance of edge points to their line, px.
    canny_max_rms_px: float = 0.8
    #: merge collinear pieces (always for Canny; for LSD only when True).
    merge_collinear: bool = False
    #: collinear merging: largest angle (deg), largest endpoint distance to the
    #: other segment's line (px) and largest gap between the pieces (px).
    merge_max_angle_deg: float = 2.0
    merge_max_distance_px: float = 1.5
    merge_max_gap_px: float = 10.0

    def __post_init__(self) -> None:
        if self.detector not in DETECTORS:
            raise ValueError(
                f"unknown detector {self.detector!r}; allowed: {', '.join(DETECTORS)}"
            )


@functools.cache
def lsd_available() -> bool:
    """Whether the installed OpenCV has a working LSD (absent in 3.4.6-4.5.0)."""
    try:
        lsd = cv2.createLineSegmentDetector()
        lsd.detect(np.zeros((16, 16), np.uint8))
    except (cv2.error, AttributeError):
        return False
    return True


# --------------------------------------------------------------------------
# Gradients and edge points
# --------------------------------------------------------------------------


def as_gray_u8(image: np.ndarray) -> np.ndarray:
    """A (H, W) uint8 grayscale view of a (H, W) or (H, W, 3) BGR image."""
    image = np.asarray(image)
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    if image.ndim != 2:
        raise ValueError(f"expected a (H, W) grayscale image, got shape {image.shape}")
    if image.dtype != np.uint8:
        image = np.clip(image, 0, 255).astype(np.uint8)
    return image


def equalize_local_contrast(
    image: np.ndarray, clip_limit: float, tiles: int
) -> np.ndarray:
    """(H, W) uint8 image with its contrast equalised per region (CLAHE:
    ``tiles`` x ``tiles`` regions, each histogram clipped at ``clip_limit``
    times the uniform share, interpolated between regions).

    A facade in shadow gets the contrast of one in the sun, so absolute
    thresholds find its edges. The mapping is nonlinear in the grey level,
    which bends a blurred edge's profile and moves its sub-pixel position by
    a fraction of the blur: fine for finding edges and for the map corners'
    vertical segments (their residuals are ~0.9 px), not for the facade
    edges (~0.13 px).
    """
    clahe = cv2.createCLAHE(clipLimit=float(clip_limit), tileGridSize=(tiles, tiles))
    return clahe.apply(as_gray_u8(image))


def gradients(
    image: np.ndarray, sigma_px: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Image gradient (gx, gy) in grey levels per pixel, float32 (H, W) each.

    3x3 Sobel divided by 8 (so a linear ramp of slope 1 gives 1), after an
    optional Gaussian blur of ``sigma_px``.
    """
    img = image.astype(np.float32)
    if sigma_px > 0:
        img = cv2.GaussianBlur(img, (0, 0), sigma_px)
    gx = cv2.Sobel(img, cv2.CV_32F, 1, 0, ksize=3, scale=0.125)
    gy = cv2.Sobel(img, cv2.CV_32F, 0, 1, ksize=3, scale=0.125)
    return gx, gy


@dataclass
class EdgePoints:
    """Sub-pixel edge points after non-maximum suppression and hysteresis.

    Attributes
    ----------
    xy : (M, 2) float array, COLMAP pixels.
    derivative : (M,) float array, signed derivative along ``normal``,
        grey levels per pixel (positive: brighter on the ``+normal`` side).
    normal : (M, 2) float array, unit direction of the derivative.
    group : (M,) int array, connected chain of same-sign points, 0..G-1.
    """

    xy: np.ndarray
    derivative: np.ndarray
    normal: np.ndarray
    group: np.ndarray

    @property
    def n_groups(self) -> int:
        return int(self.group.max()) + 1 if len(self.group) else 0


# Neighbour steps of the four quantised NMS directions (dx, dy).
_NMS_STEPS = np.array([[1, 0], [1, 1], [0, 1], [-1, 1]])
_TAN_22_5 = np.float32(np.tan(np.pi / 8))


def edge_points(
    gx: np.ndarray,
    gy: np.ndarray,
    normal_at,
    low: float,
    high: float,
    max_angle_deg: float = 90.0,
) -> EdgePoints:
    """Canny-style edge points of a directional derivative.

    1. ``normal_at(x, y, gx, gy)`` gives the unit direction field
       ``(nx, ny)`` along which the derivative D = g . normal is taken.
    2. Candidates: pixels with |D| >= ``low`` whose gradient leaves the
       normal by at most ``max_angle_deg`` (this suppresses strong but wrongly
       oriented gradients).
    3. Non-maximum suppression of |D| along the normal quantised to the 8
       neighbours, and a Gaussian through the three values for the sub-pixel
       position (the peak along any direction that crosses a straight edge
       lies on it).
    4. Hysteresis: 8-connected chains of equal sign are kept when their
       largest |D| reaches ``high``.

    Steps 1 and 2 run on whole images (contiguous float32 arithmetic, no
    gathers): cheaper than selecting the candidates first, since half of a
    textured image passes the gradient threshold.

    Parameters
    ----------
    gx, gy : (H, W) float32 arrays, grey levels per pixel (:func:`gradients`).
    normal_at : callable ``(x, y, gx, gy) -> (nx, ny)``: x (1, W) and y (H, 1)
        float32 pixel-centre coordinates (COLMAP pixels), gx, gy as above;
        nx, ny float32 arrays broadcastable to (H, W).
    low, high : float, thresholds on |D|, grey levels per pixel.
    max_angle_deg : float, largest angle between gradient and normal.

    Returns
    -------
    EdgePoints
    """
    H, W = gx.shape
    mag = cv2.magnitude(gx, gy)  # (H, W) float32
    # Stay one pixel off the border so that every neighbour exists.
    mag[0, :] = mag[-1, :] = 0
    mag[:, 0] = mag[:, -1] = 0
    x = np.arange(W, dtype=np.float32)[None, :] + np.float32(PIXEL_CENTER_OFFSET)
    y = np.arange(H, dtype=np.float32)[:, None] + np.float32(PIXEL_CENTER_OFFSET)
    nxg, nyg = normal_at(x, y, gx, gy)
    nxg = np.broadcast_to(nxg, (H, W))
    nyg = np.broadcast_to(nyg, (H, W))
    # Two full-image float buffers, reused: at 4008 x 2672 every fresh
    # 43 MB temporary costs more in page faults than its arithmetic.
    D = np.multiply(gx, nxg)
    buf = np.multiply(gy, nyg)
    D += buf
    ad = np.abs(D, out=buf)
    cos_min = np.float32(np.cos(np.radians(max_angle_deg)))
    cand = mag >= low
    cand &= ad >= low
    lim = np.multiply(mag, cos_min)
    lim -= 1e-6
    cand &= ad >= lim
    del lim, buf, ad
    idx = np.flatnonzero(cand)
    gxf, gyf = gx.reshape(-1), gy.reshape(-1)
    d0 = D.reshape(-1)[idx]
    nx = nxg.reshape(-1)[idx] if nxg.flags.c_contiguous else nxg.flat[idx]
    ny = nyg.reshape(-1)[idx] if nyg.flags.c_contiguous else nyg.flat[idx]

    # 3. NMS along the quantised normal (directions mod pi -> 4 bins of
    # 45 deg centred on 0, 45, 90, 135 deg; comparisons instead of arctan2).
    anx, any_ = np.abs(nx), np.abs(ny)
    k = np.where(nx * ny > 0, 1, 3)
    k[any_ <= _TAN_22_5 * anx] = 0
    k[anx < _TAN_22_5 * any_] = 2
    sx, sy = _NMS_STEPS[k, 0], _NMS_STEPS[k, 1]
    off = sx + sy * W
    s = np.sign(d0)
    snx, sny = s * nx, s * ny
    a = gxf[idx - off] * snx + gyf[idx - off] * sny
    c = gxf[idx + off] * snx + gyf[idx + off] * sny
    b = np.abs(d0)
    peak = np.flatnonzero((b >= c) & (b > a))
    idx, nx, ny, d0 = idx[peak], nx[peak], ny[peak], d0[peak]
    a, b, c, sx, sy = a[peak], b[peak], c[peak], sx[peak], sy[peak]
    rows, cols = np.divmod(idx, W)
    x = cols.astype(np.float32) + np.float32(PIXEL_CENTER_OFFSET)
    y = rows.astype(np.float32) + np.float32(PIXEL_CENTER_OFFSET)
    # Gaussian peak (a parabola through the logarithms): exact for the
    # Gaussian-blurred step, whose plain parabola fit is biased by up to
    # ~0.05 px depending on the sub-pixel phase; plain parabola where a
    # neighbour is not positive.
    tiny = np.float32(1e-6)
    pos = (a > tiny) & (c > tiny)
    la = np.log(np.maximum(a, tiny))
    lb = np.log(np.maximum(b, tiny))
    lc = np.log(np.maximum(c, tiny))
    a, b, c = np.where(pos, la, a), np.where(pos, lb, b), np.where(pos, lc, c)
    denom = a - 2 * b + c  # < 0 at a strict maximum
    t = 0.5 * (a - c) / np.where(denom < 0, denom, np.float32(-1))
    t = np.clip(np.where(denom < 0, t, 0), -0.5, 0.5)
    xy = np.stack([x + t * sx, y + t * sy], axis=1).astype(float)

    # 4. Hysteresis on 8-connected chains, split by sign.
    mask = np.zeros((H, W), np.uint8)
    mask.reshape(-1)[idx] = 1
    n_lab, labels = cv2.connectedComponents(mask, connectivity=8, ltype=cv2.CV_32S)
    key = labels.reshape(-1)[idx].astype(np.int64) * 2 + (d0 < 0)
    strong = np.zeros(2 * n_lab, bool)
    strong[key[np.abs(d0) >= high]] = True
    keep = strong[key]
    group = (np.cumsum(strong) - 1)[key[keep]]
    return EdgePoints(
        xy=xy[keep],
        derivative=d0[keep].astype(float),
        normal=np.stack([nx[keep], ny[keep]], axis=1).astype(float),
        group=group,
    )


# --------------------------------------------------------------------------
# Group statistics and line fits
# --------------------------------------------------------------------------


def scatter_matrices(
    xy: np.ndarray, group: np.ndarray, n_groups: int, weights: np.ndarray | None = None
) -> np.ndarray:
    """Per-group second moments of homogeneous points.

    Parameters
    ----------
    xy : (M, 2) array of (normalised) coordinates.
    group : (M,) int array in 0..n_groups-1.
    weights : (M,) array or None.

    Returns
    -------
    (G, 3, 3) array ``sum_i w_i p_i p_i^T`` with ``p_i = (x, y, 1)``.
    """
    x, y = xy[:, 0], xy[:, 1]
    w = np.ones(len(xy)) if weights is None else weights
    terms = (x * x, x * y, x, y * y, y, np.ones_like(x))
    sums = [np.bincount(group, weights=w * t, minlength=n_groups) for t in terms]
    xx, xy_, x1, yy, y1, n1 = sums
    S = np.empty((n_groups, 3, 3))
    S[:, 0, 0], S[:, 0, 1], S[:, 0, 2] = xx, xy_, x1
    S[:, 1, 1], S[:, 1, 2], S[:, 2, 2] = yy, y1, n1
    S[:, 1, 0], S[:, 2, 0], S[:, 2, 1] = xy_, x1, y1
    return S


def fit_lines(S: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Total-least-squares lines from (G, 3, 3) scatter matrices.

    Returns
    -------
    lines : (G, 3) array ``(a, b, c)`` with unit normal (a, b).
    cost : (G,) array, sum of squared point-to-line distances.
    """
    n = np.maximum(S[:, 2, 2], 1e-300)
    mx, my = S[:, 0, 2] / n, S[:, 1, 2] / n
    cxx = S[:, 0, 0] - n * mx * mx
    cxy = S[:, 0, 1] - n * mx * my
    cyy = S[:, 1, 1] - n * my * my
    # Smallest eigenvector of the 2x2 covariance [[cxx, cxy], [cxy, cyy]].
    half_tr = 0.5 * (cxx + cyy)
    disc = np.sqrt(np.maximum(0.25 * (cxx - cyy) ** 2 + cxy * cxy, 0.0))
    lam = half_tr - disc
    # Normal (a, b) is the eigenvector of lam; choose the better-conditioned form.
    a1, b1 = cxy, lam - cxx
    a2, b2 = lam - cyy, cxy
    use1 = a1 * a1 + b1 * b1 >= a2 * a2 + b2 * b2
    a, b = np.where(use1, a1, a2), np.where(use1, b1, b2)
    norm = np.hypot(a, b)
    degenerate = norm < 1e-300
    a = np.where(degenerate, 1.0, a / np.where(degenerate, 1.0, norm))
    b = np.where(degenerate, 0.0, b / np.where(degenerate, 1.0, norm))
    c = -(a * mx + b * my)
    return np.stack([a, b, c], axis=1), np.maximum(lam, 0.0)


def segment_extents(
    xy: np.ndarray, group: np.ndarray, lines: np.ndarray, n_groups: int
) -> np.ndarray:
    """(G, 2, 2) endpoints: the feet of each group's extreme points on its line."""
    normal = lines[:, :2]
    tangent = np.stack([-normal[:, 1], normal[:, 0]], axis=1)
    s = np.sum(xy * tangent[group], axis=1)
    smin = np.full(n_groups, np.inf)
    smax = np.full(n_groups, -np.inf)
    np.minimum.at(smin, group, s)
    np.maximum.at(smax, group, s)
    foot = -lines[:, 2:3] * normal  # (G, 2) the point of the line nearest 0
    return np.stack(
        [foot + smin[:, None] * tangent, foot + smax[:, None] * tangent], axis=1
    )


def _group_order(group: np.ndarray, s: np.ndarray) -> np.ndarray:
    """The permutation sorting points by (group, s), (M,) int.

    One argsort of the float key ``group * span + (s - min s)`` with ``span``
    twice the range of s (groups cannot interleave): several times faster
    than ``np.lexsort((s, group))``; points of one group whose s agree to
    ~1e-16 of the key may come in either order.
    """
    if len(s) == 0:
        return np.zeros(0, np.int64)
    lo = s.min()
    span = 2.0 * (s.max() - lo) + 1e-12
    return np.argsort(group * span + (s - lo))


def split_at_gaps(
    xy: np.ndarray, group: np.ndarray, tangent: np.ndarray, max_gap: float
) -> tuple[np.ndarray, np.ndarray]:
    """Split groups where consecutive points along ``tangent`` are far apart.

    Parameters
    ----------
    xy : (M, 2) points; group : (M,) ids; tangent : (G, 2) unit directions.
    max_gap : float, largest gap kept inside one group (same unit as xy).

    Returns
    -------
    new_group : (M,) compact ids; order : (M,) the permutation sorting the
        points by (group, position) that the ids refer to (``xy[order]``).
    """
    t = tangent[group]
    s = xy[:, 0] * t[:, 0] + xy[:, 1] * t[:, 1]
    order = _group_order(group, s)
    g, s = group[order], s[order]
    brk = np.ones(len(g), bool)
    brk[1:] = (g[1:] != g[:-1]) | (np.diff(s) > max_gap)
    return np.cumsum(brk) - 1, order


# --------------------------------------------------------------------------
# Polarity and strength by sampling the gradient
# --------------------------------------------------------------------------


def bilinear(img: np.ndarray, xy: np.ndarray) -> np.ndarray:
    """Bilinear samples of (H, W) ``img`` at (K, 2) COLMAP pixel positions."""
    return bilinear_many((img,), xy)[0]


def bilinear_many(imgs, xy: np.ndarray) -> list[np.ndarray]:
    """Bilinear samples (K,) of each (H, W) image of ``imgs`` at (K, 2) positions.

    The images share one shape; indices and weights are computed once.
    """
    H, W = imgs[0].shape
    x = np.clip(xy[:, 0] - PIXEL_CENTER_OFFSET, 0, W - 1.001)
    y = np.clip(xy[:, 1] - PIXEL_CENTER_OFFSET, 0, H - 1.001)
    x0, y0 = x.astype(np.int64), y.astype(np.int64)
    fx, fy = x - x0, y - y0
    i = y0 * W + x0
    w00, w01 = (1 - fx) * (1 - fy), fx * (1 - fy)
    w10, w11 = (1 - fx) * fy, fx * fy
    out = []
    for img in imgs:
        f = img.reshape(-1)
        out.append(f[i] * w00 + f[i + 1] * w01 + f[i + W] * w10 + f[i + W + 1] * w11)
    return out


def polarity_and_strength(
    endpoints: np.ndarray, gx: np.ndarray, gy: np.ndarray, n_samples: int = 8
) -> tuple[np.ndarray, np.ndarray]:
    """Bright-side normals (N, 2) and mean cross-gradient (N,) of segments.

    The gradient is sampled at ``n_samples`` points evenly spread over the
    interior of each segment (COLMAP pixels of the gradient images).
    """
    if len(endpoints) == 0:
        return np.zeros((0, 2)), np.zeros(0)
    p0, p1 = endpoints[:, 0], endpoints[:, 1]
    d = p1 - p0
    length = np.linalg.norm(d, axis=1, keepdims=True)
    d = d / np.where(length > 0, length, 1.0)
    left = np.stack([d[:, 1], -d[:, 0]], axis=1)
    f = (np.arange(n_samples) + 0.5) / n_samples
    pts = p0[:, None, :] + f[None, :, None] * (p1 - p0)[:, None, :]  # (N, S, 2)
    flat = pts.reshape(-1, 2)
    g = np.stack(bilinear_many((gx, gy), flat), axis=1)
    cross = np.sum(g.reshape(len(d), n_samples, 2) * left[:, None, :], axis=2).mean(1)
    sign = np.where(cross >= 0, 1.0, -1.0)
    return left * sign[:, None], np.abs(cross)


# --------------------------------------------------------------------------
# Sub-pixel refit on the full-resolution image
# --------------------------------------------------------------------------


@dataclass(kw_only=True)
class RefineOptions:
    """Options of :func:`refine_segments`."""

    #: Half-width of the intensity profile across the segment, pixels of the
    #: image the segments were DETECTED in (``Segments.pixel_scale``: LSD's
    #: errors live there, and the profile must reach past them). Window rows
    #: and frames lie a few pixels apart on an aerial facade: at 2 px the
    #: neighbouring edge stays out of the plateaus (measured on `paper` seeds 1
    #: and 2: facade-track noise at the true cameras p50 0.13 -> 0.08 px,
    #: against 0.10-0.12 px at 3 px).
    radius_px: float = 2.0
    #: Sample spacing across (px).
    step_px: float = 0.5
    #: Spacing of the profiles along the segment (px).
    station_px: float = 1.0
    #: Profiles whose edge lies farther than this from the fitted line (px)
    #: are dropped from the fit (a crossing edge, a window corner).
    max_residual_px: float = 0.5
    #: Fewest profiles a refit needs; else the segment is kept as it is.
    min_stations: int = 5
    #: A refit that moves an endpoint farther than this (px of the detection
    #: image) is refused.
    max_move_px: float = 1.5
    #: Refits, each sampling about the previous one (LSD's ~0.3 px offsets
    #: shrink to ~0.02 px in three).
    rounds: int = 3

    def __post_init__(self) -> None:
        if not (0 < self.step_px < self.radius_px and self.station_px > 0):
            raise ValueError("need 0 < step_px < radius_px and station_px > 0")


def _remap_linear(img: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples of float32 ``img`` at COLMAP pixels ``x, y`` (S, O).

    OpenCV's remap (an order faster than numpy gathers; it rounds positions
    to 1/32 px); its maps must have fewer than 32767 rows, hence the chunks.
    """
    out = np.empty(x.shape, np.float32)
    for r in range(0, len(x), 32000):
        out[r : r + 32000] = cv2.remap(
            img,
            x[r : r + 32000] - np.float32(PIXEL_CENTER_OFFSET),
            y[r : r + 32000] - np.float32(PIXEL_CENTER_OFFSET),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_REPLICATE,
        )
    return out


def _edge_offsets(
    profiles: np.ndarray, offsets: np.ndarray, step: float
) -> tuple[np.ndarray, np.ndarray]:
    """Edge position (S,) and contrast weight (S,) of rising profiles (S, O).

    The edge is where the profile crosses the middle of its two plateaus
    (the outer samples within 1 px of each end), the crossing nearest the
    centre, linearly interpolated; the weight is the plateaus' contrast (0
    where there is no rising crossing). Unbiased for an edge at the centre;
    an edge off it pulls its near plateau, so :func:`refine_segments`
    samples again about each refit (the offset shrinks ~2.3x per round).
    """
    m = max(1, int(round(1.0 / step))) + 1
    lo = profiles[:, :m].mean(axis=1)
    hi = profiles[:, -m:].mean(axis=1)
    mid = 0.5 * (lo + hi)
    above = profiles >= mid[:, None]
    cross = above[:, 1:] & ~above[:, :-1]
    centre = np.abs(0.5 * (offsets[1:] + offsets[:-1]))
    k = np.argmin(np.where(cross, centre[None], np.inf), axis=1)
    rows = np.arange(len(k))
    ok = cross[rows, k]
    a, b = profiles[rows, k], profiles[rows, k + 1]
    frac = (mid - a) / np.where(b > a, b - a, 1.0)
    edge = offsets[k] + frac * step
    return edge, np.where(ok, np.maximum(hi - lo, 0.0), 0.0)


def refine_segments(
    image: np.ndarray,
    segments: Segments,
    camera: Camera | None = None,
    options: RefineOptions | None = None,
) -> Segments:
    """Segments refitted to the image's edges with sub-pixel accuracy.

    LSD localises an edge to a few tenths of a pixel (and at reduced
    resolution for big images); the facade constraints of the bundle are
    read from the segments' lines, so their noise goes straight into the
    cameras. Here every segment is resampled on the full-resolution image:
    intensity profiles across it every ``station_px``, the edge position of
    each profile (:func:`_edge_offsets`), and a weighted, trimmed line fit
    ``offset = a + b s`` along the segment's normal. Endpoints keep their
    position along the segment. Segments without enough profiles, or whose
    refit moves more than ``max_move_px``, are returned unchanged.

    Parameters
    ----------
    image : (H, W) uint8 or float array, the image as seen (raw pixels).
    segments : Segments in the UNDISTORTED pixels of ``camera`` (raw pixels
        when ``camera`` is None or has no distortion): the profiles are
        straight there and are sampled through the camera's distortion.
    options : RefineOptions or None for the defaults.

    Returns
    -------
    Segments with new endpoints, the same normals, strengths and
    ``pixel_scale``.
    """
    options = options or RefineOptions()
    K = len(segments)
    if K == 0:
        return segments
    img = np.asarray(as_gray_u8(image) if image.ndim == 3 else image, np.float32)
    distort = camera is not None and camera.has_distortion
    ends = segments.endpoints.copy()
    radius = options.radius_px * segments.pixel_scale
    offsets = np.arange(-radius, radius + 1e-9, options.step_px)
    for _ in range(options.rounds):
        d = ends[:, 1] - ends[:, 0]
        length = np.linalg.norm(d, axis=1)
        d = d / np.where(length > 0, length, 1.0)[:, None]
        n = np.stack([-d[:, 1], d[:, 0]], axis=1)
        # profiles rise towards the brighter side
        n = n * np.where(np.sum(n * segments.normal, axis=1) < 0, -1.0, 1.0)[:, None]
        station = options.station_px
        count = np.maximum(np.floor(length / station - 2).astype(np.int64) + 1, 0)
        seg = np.repeat(np.arange(K), count)
        first = np.repeat(np.cumsum(count) - count, count)
        s = station * (1 + np.arange(len(seg)) - first)  # (S,) along from end 0
        base = (ends[seg, 0] + s[:, None] * d[seg]).astype(np.float32)
        ns = n[seg].astype(np.float32)
        o = offsets.astype(np.float32)[None, :]
        x = base[:, :1] + o * ns[:, :1]  # (S, O)
        y = base[:, 1:] + o * ns[:, 1:]
        if distort:
            raw = camera.distort_pixels(np.column_stack([x.ravel(), y.ravel()]))
            x = raw[:, 0].reshape(x.shape).astype(np.float32)
            y = raw[:, 1].reshape(y.shape).astype(np.float32)
        prof = _remap_linear(img, x, y)
        edge, w = _edge_offsets(prof, offsets, options.step_px)
        for _ in range(3):  # weighted line fit, trimmed twice
            W = np.bincount(seg, w, K)
            Wsafe = np.where(W > 0, W, 1.0)
            s_mean = np.bincount(seg, w * s, K) / Wsafe
            sc = s - s_mean[seg]
            a = np.bincount(seg, w * edge, K) / Wsafe
            Sss = np.bincount(seg, w * sc * sc, K)
            b = np.bincount(seg, w * sc * edge, K) / np.where(Sss > 0, Sss, 1.0)
            res = edge - a[seg] - b[seg] * sc
            w = np.where(np.abs(res) > options.max_residual_px, 0.0, w)
        stations = np.bincount(seg, w > 0, K)
        shift = np.stack([a - b * s_mean, a + b * (length - s_mean)], axis=1)
        new = ends + shift[:, :, None] * n[:, None, :]
        move = np.linalg.norm(new - segments.endpoints, axis=2).max(axis=1)
        max_move = options.max_move_px * segments.pixel_scale
        ok = (stations >= options.min_stations) & (move <= max_move)
        ends[ok] = new[ok]
    return Segments(
        ends, segments.normal.copy(), segments.strength.copy(), segments.pixel_scale
    )


# --------------------------------------------------------------------------
# Collinear merging
# --------------------------------------------------------------------------


def merge_collinear(
    segments: Segments,
    max_angle_deg: float = 2.0,
    max_distance_px: float = 1.5,
    max_gap_px: float = 10.0,
    window: int = 8,
) -> Segments:
    """Merge pieces of one straight edge (same side brighter).

    Two segments merge when their directions differ by at most
    ``max_angle_deg``, each endpoint of the shorter lies within
    ``max_distance_px`` of the longer one's line, the gap between them along
    the line is at most ``max_gap_px`` and their normals agree. Candidates are
    the ``window`` nearest neighbours in orientation order; merging is
    transitive (connected components). A merged segment is the total-least-squares line
    of the pieces' endpoints weighted by length, cut to their extent.
    """
    n = len(segments)
    if n < 2:
        return segments
    d = segments.directions
    # Orientation mod pi, bright side kept apart via the normal check.
    ang = np.arctan2(d[:, 1], d[:, 0]) % np.pi
    order = np.argsort(ang)
    lines = segments.lines()
    L = segments.lengths
    tol = np.radians(max_angle_deg)
    # Candidate pairs (i, j) among orientation neighbours, with wrap-around.
    pos = np.arange(n)
    ii, jj = [], []
    for w in range(1, min(window, n - 1) + 1):
        ii.append(order[pos])
        jj.append(order[(pos + w) % n])
    i = np.concatenate(ii)
    j = np.concatenate(jj)
    da = np.abs(ang[i] - ang[j])
    da = np.minimum(da, np.pi - da)
    ok = (da <= tol) & (np.sum(segments.normal[i] * segments.normal[j], axis=1) > 0)
    i, j = i[ok], j[ok]
    long_ = np.where(L[i] >= L[j], i, j)
    short = np.where(L[i] >= L[j], j, i)
    dist = np.abs(
        np.einsum("nkd,nd->nk", segments.endpoints[short], lines[long_, :2])
        + lines[long_, 2:3]
    ).max(axis=1)
    t = d[long_]
    s_long = np.einsum("nkd,nd->nk", segments.endpoints[long_], t)
    s_short = np.einsum("nkd,nd->nk", segments.endpoints[short], t)
    gap = np.maximum(s_short.min(1) - s_long.max(1), s_long.min(1) - s_short.max(1))
    ok = (dist <= max_distance_px) & (gap <= max_gap_px)
    G, group = connected_pairs(n, i[ok], j[ok])
    if n == G:
        return segments
    pts = segments.endpoints.reshape(-1, 2)
    gpts = np.repeat(group, 2)
    w = np.repeat(L, 2)
    S = scatter_matrices(pts, gpts, G, weights=w)
    fitted, _ = fit_lines(S)
    ends = segment_extents(pts, gpts, fitted, G)
    # Normal: the length-weighted mean of the pieces, projected on the fit.
    nsum = np.zeros((G, 2))
    np.add.at(nsum, group, segments.normal * L[:, None])
    normal = fitted[:, :2] * np.sign(np.sum(fitted[:, :2] * nsum, axis=1))[:, None]
    strength = np.bincount(group, weights=segments.strength * L, minlength=G)
    strength /= np.bincount(group, weights=L, minlength=G)
    return Segments(ends, normal, strength)


def connected_pairs(n: int, i: np.ndarray, j: np.ndarray) -> tuple[int, np.ndarray]:
    """Transitive groups of n items linked by pairs (i, j).

    Label propagation with pointer jumping (a few vectorised rounds).

    Returns
    -------
    count : int; group : (n,) ids 0..count-1.
    """
    label = np.arange(n)
    i, j = np.asarray(i, np.int64), np.asarray(j, np.int64)
    while len(i):
        m = np.minimum(label[i], label[j])
        new = label.copy()
        np.minimum.at(new, i, m)
        np.minimum.at(new, j, m)
        new = new[new]
        while True:  # pointer jumping to the roots
            nxt = new[new]
            if np.array_equal(nxt, new):
                break
            new = nxt
        if np.array_equal(new, label):
            break
        label = new
    uniq, group = np.unique(label, return_inverse=True)
    return len(uniq), group


# --------------------------------------------------------------------------
# Detection
# --------------------------------------------------------------------------


def _detect_lsd(img: np.ndarray, options: LineOptions) -> np.ndarray:
    """(N, 2, 2) LSD endpoints in COLMAP pixels of ``img``."""
    refine = cv2.LSD_REFINE_STD if options.lsd_refine else cv2.LSD_REFINE_NONE
    lsd = cv2.createLineSegmentDetector(refine, options.lsd_scale)
    raw = lsd.detect(img)[0]
    if raw is None:
        return np.zeros((0, 2, 2))
    # OpenCV 5 returns (N, 4), OpenCV 4 (N, 1, 4).
    ends = np.asarray(raw, float).reshape(-1, 2, 2)
    # LSD: pixel centres at integers, and its sub-sampling by `scale` maps
    # x_small = (x + 0.5) scale - 0.5 but reports x_small / scale.
    return ends + 0.5 / options.lsd_scale


def _detect_canny(
    img: np.ndarray, gx: np.ndarray, gy: np.ndarray, options: LineOptions
) -> Segments:
    """Canny edge points -> orientation-consistent chains -> LSQ lines."""

    def along_gradient(x, y, gx_, gy_):
        m = np.maximum(np.hypot(gx_, gy_), np.float32(1e-12))
        return gx_ / m, gy_ / m

    pts = edge_points(gx, gy, along_gradient, options.canny_low, options.canny_high)
    if len(pts.xy) == 0:
        return Segments()
    theta = np.arctan2(pts.normal[:, 1], pts.normal[:, 0])  # polarity-aware
    parts = []
    # Two binnings of 45 deg offset by half a bin: a straight edge stays in
    # one bin of at least one of them; duplicates are merged afterwards.
    for shift in (0.0, np.pi / 8):
        b = np.floor(((theta + shift) % (2 * np.pi)) / (np.pi / 4)).astype(np.int64)
        key = pts.group * 8 + b
        uniq, grp = np.unique(key, return_inverse=True)
        G = len(uniq)
        S = scatter_matrices(pts.xy, grp, G)
        lines, _ = fit_lines(S)
        # Drop points far from their group's line, refit, split at gaps.
        r = np.abs(np.sum(pts.xy * lines[grp, :2], axis=1) + lines[grp, 2])
        good = r <= 2.0 * options.canny_max_rms_px + 0.5
        xy, grp = pts.xy[good], grp[good]
        tangent = np.stack([-lines[:, 1], lines[:, 0]], axis=1)
        grp, order = split_at_gaps(xy, grp, tangent, 2.5)
        xy = xy[order]
        G = int(grp.max()) + 1 if len(grp) else 0
        S = scatter_matrices(xy, grp, G)
        lines, cost = fit_lines(S)
        count = S[:, 2, 2]
        ends = segment_extents(xy, grp, lines, G)
        length = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1)
        rms = np.sqrt(cost / np.maximum(count, 1))
        ok = (
            (length >= options.min_length_px)
            & (rms <= options.canny_max_rms_px)
            & (count >= 0.5 * length)
        )
        parts.append(ends[ok])
    ends = np.concatenate(parts) if parts else np.zeros((0, 2, 2))
    normal, strength = polarity_and_strength(ends, gx, gy)
    segs = Segments(ends, normal, strength)
    return merge_collinear(
        segs,
        options.merge_max_angle_deg,
        options.merge_max_distance_px,
        options.merge_max_gap_px,
    )


def detect_segments(image: np.ndarray, options: LineOptions | None = None) -> Segments:
    """Straight line segments of an image.

    Parameters
    ----------
    image : (H, W) uint8 grayscale array (or (H, W, 3) BGR).
    options : LineOptions or None for the defaults.

    Returns
    -------
    Segments
        Endpoints in COLMAP pixels of the full-resolution image (distorted,
        i.e. as seen; see :meth:`Segments.undistorted`), bright-side normals,
        strengths measured at the detection resolution.
    """
    options = options or LineOptions()
    img = as_gray_u8(image)
    H, W = img.shape
    factor = 1.0
    limit = options.max_image_size_px
    if limit and max(H, W) > limit:
        factor = max(H, W) / limit
        size = (max(1, round(W / factor)), max(1, round(H / factor)))
        img = cv2.resize(img, size, interpolation=cv2.INTER_AREA)
    detector = options.detector
    if detector == "auto":
        detector = "lsd" if lsd_available() else "canny"
    if detector == "lsd":
        ends = _detect_lsd(img, options)
        L = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1)
        ends = ends[options.min_length_px <= L]
        gx, gy = gradients(img)
        normal, strength = polarity_and_strength(ends, gx, gy)
        segs = Segments(ends, normal, strength)
        if options.merge_collinear:
            segs = merge_collinear(
                segs,
                options.merge_max_angle_deg,
                options.merge_max_distance_px,
                options.merge_max_gap_px,
            )
    else:
        gx, gy = gradients(img, options.canny_sigma_px)
        segs = _detect_canny(img, gx, gy, options)
    # Resizing in COLMAP pixels is a pure scale (pixel edges at integers).
    sx, sy = W / img.shape[1], H / img.shape[0]
    if sx != 1.0 or sy != 1.0:
        segs.endpoints = segs.endpoints * np.array([sx, sy])
        segs.pixel_scale = max(sx, sy)
    logger.debug(
        "%d segments (%s, detection at %dx%d)",
        len(segs),
        detector,
        img.shape[1],
        img.shape[0],
    )
    return segs
