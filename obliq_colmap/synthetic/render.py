"""A vectorised z-buffer rasteriser and the image formation of the synthetic camera.

Pipeline of :func:`render_image`:

1. raster: the city mesh is rasterised into an undistorted pinhole "canvas"
   at ``supersample`` times the output resolution (scan-line spans per
   triangle row, all triangles at once in numpy; near-plane, frustum and
   back-face culling; z-test on the exact inverse depth of each triangle's
   plane at the pixel centre).
2. shade: the exact 3D point of every canvas pixel (from its depth) gives the
   procedural albedo (:mod:`obliq_colmap.synthetic.shading`), lit by a sun.
3. post: box filter down to the output resolution (anti-aliasing), lens
   distortion by ``cv2.remap`` through :func:`obliq_colmap.geometry.cam_from_img`
   (so that :func:`obliq_colmap.geometry.project` of a 3D point lands on its
   rendered pixel), vignetting, Gaussian optical blur, sensor noise.

Pixel convention (COLMAP's, see :mod:`obliq_colmap.geometry`): the centre of
the top-left pixel is at (0.5, 0.5). A canvas pixel (row i, col j) has its
centre at (j + 0.5, i + 0.5) canvas pixels, and canvas coordinates are
``s * output_coordinates - offset`` for supersampling factor ``s``, so the
``s x s`` canvas pixels of output pixel (r, c) are exactly rows ``s r ..
s r + s - 1`` (without offset), and their box average is the output pixel.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np

from obliq_colmap.geometry import Camera, Pose
from obliq_colmap.synthetic.city import City
from obliq_colmap.synthetic.options import SceneOptions
from obliq_colmap.synthetic.shading import shade, sun_direction

NEAR_M = 1.0
_CHUNK = 3_000_000  # fragments per z-buffer pass (memory bound)


@dataclass
class Canvas:
    """An undistorted pinhole raster: canvas px = fx * X / Z + cx, etc."""

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int


@dataclass
class Raster:
    """Result of :func:`rasterize` on a canvas.

    inv_depth : (H, W) float64, 1 / camera z of the nearest surface, 0 = empty.
    face_id : (H, W) int32, -1 = empty.
    planes : (F, 3) float64 inverse-depth plane coefficients of every face of
        the city (see :func:`face_planes`), NaN for culled faces.
    """

    inv_depth: np.ndarray
    face_id: np.ndarray
    planes: np.ndarray


def face_planes(
    city: City, pose: Pose, canvas: Canvas, faces: np.ndarray
) -> np.ndarray:
    """(N, 3) coefficients (A, B, C) with 1 / z = A x + B y + C on each face's plane.

    x, y are canvas pixel coordinates. For the plane n . X = d (camera frame)
    and the ray X = z (x_n, y_n, 1): 1 / z = n . (x_n, y_n, 1) / d.
    """
    n = city.face_normal[faces] @ pose.rotation.T
    X0 = city.vertices[city.faces[faces, 0]] @ pose.rotation.T + pose.translation
    d = np.einsum("ij,ij->i", n, X0)
    with np.errstate(divide="ignore", invalid="ignore"):
        A = n[:, 0] / (canvas.fx * d)
        B = n[:, 1] / (canvas.fy * d)
        Cc = (
            n[:, 2] - n[:, 0] * canvas.cx / canvas.fx - n[:, 1] * canvas.cy / canvas.fy
        ) / d
    return np.stack([A, B, Cc], 1)


def _cut_edges(Xc: np.ndarray, ia: np.ndarray, ib: np.ndarray) -> np.ndarray:
    """(n, 3) points where the edges (ia, ib) of ``Xc`` cross z = NEAR_M.

    Interpolated from the lower vertex index, so that two triangles sharing
    an edge get bit-identical points (no cracks).
    """
    lo, hi = np.minimum(ia, ib), np.maximum(ia, ib)
    A, B = Xc[lo], Xc[hi]
    t = (A[:, 2] - NEAR_M) / (A[:, 2] - B[:, 2])
    out = A + t[:, None] * (B - A)
    out[:, 2] = NEAR_M
    return out


def clip_near(
    Xc: np.ndarray, faces: np.ndarray, front: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Clip triangles with one or two vertices in front of the near plane.

    Parameters
    ----------
    Xc : (V, 3) camera-frame vertices.
    faces : (n, 3) vertex indices; front : (n, 3) bool, vertex z > NEAR_M.

    Returns
    -------
    P : (m, 3, 3) camera-frame triangles in front (the winding kept) ...
    parent : (m,) ... and the row of ``faces`` each comes from.
    """
    one = front.sum(1) == 1
    # Roll each triangle so that its odd vertex (the only one in front, or
    # the only one behind) comes first; rolling keeps the winding.
    odd = np.where(one[:, None], front, ~front)
    k = np.argmax(odd, axis=1)
    f = np.take_along_axis(faces, (k[:, None] + np.arange(3)) % 3, axis=1)
    a, b, c = f[:, 0], f[:, 1], f[:, 2]
    ab, ac = _cut_edges(Xc, a, b), _cut_edges(Xc, a, c)
    n = np.arange(len(f))
    # one in front: the triangle (a, ab, ac)
    t1 = np.stack([Xc[a], ab, ac], 1)[one]
    # two in front: the quad (ab, b, c, ac) as two triangles
    two = ~one
    t2 = np.stack([ab, Xc[b], Xc[c]], 1)[two]
    t3 = np.stack([ab, Xc[c], ac], 1)[two]
    P = np.concatenate([t1, t2, t3])
    parent = np.concatenate([n[one], n[two], n[two]])
    return P, parent


def rasterize(city: City, pose: Pose, canvas: Canvas) -> Raster:
    """Z-buffer rasterisation of the city mesh into ``canvas``.

    A pixel belongs to a triangle when its centre lies inside (inclusive),
    so triangles sharing an edge leave no cracks; the nearest surface wins.

    Parameters
    ----------
    city : the mesh (local frame).
    pose : cam_from_world, local frame.
    canvas : pinhole canvas geometry.

    Returns
    -------
    Raster.
    """
    W, H = canvas.width, canvas.height
    R, t = pose.rotation, pose.translation
    Xc = city.vertices @ R.T + t  # (V, 3) camera frame
    F = city.faces
    front = Xc[F, 2] > NEAR_M  # (F, 3)
    n_front = front.sum(1)
    # Back-face culling: the outward normal must point towards the camera.
    n_cam = city.face_normal @ R.T
    facing = np.einsum("ij,ij->i", n_cam, Xc[F[:, 0]]) < 0
    idx = np.nonzero(facing & (n_front == 3))[0]
    P = Xc[F[idx]]  # (n, 3, 3)
    # A camera inside the city (a street view) sees triangles cut by the
    # near plane (the ground under its feet): clip them instead of dropping.
    cut = np.nonzero(facing & (n_front > 0) & (n_front < 3))[0]
    if len(cut):
        P_cut, parent = clip_near(Xc, F[cut], front[cut])
        idx = np.concatenate([idx, cut[parent]])
        P = np.concatenate([P, P_cut])
    x = canvas.fx * P[..., 0] / P[..., 2] + canvas.cx
    y = canvas.fy * P[..., 1] / P[..., 2] + canvas.cy
    j0 = np.maximum(np.ceil(y.min(1) - 0.5), 0).astype(np.int64)
    j1 = np.minimum(np.floor(y.max(1) - 0.5), H - 1).astype(np.int64)
    xl_all = np.ceil(x.min(1) - 0.5)
    xr_all = np.floor(x.max(1) - 0.5)
    vis = (j1 >= j0) & (xr_all >= 0) & (xl_all <= W - 1)
    idx, x, y, j0, j1 = idx[vis], x[vis], y[vis], j0[vis], j1[vis]
    planes = face_planes(city, pose, canvas, idx)
    all_planes = np.full((len(F), 3), np.nan)
    all_planes[idx] = planes

    # Edges in canonical order (lower y first, then lower x) so that two
    # triangles sharing an edge compute bit-identical span ends.
    edges = []
    for a, b in ((0, 1), (1, 2), (2, 0)):
        xa, ya, xb, yb = x[:, a], y[:, a], x[:, b], y[:, b]
        swap = (ya > yb) | ((ya == yb) & (xa > xb))
        xa, xb = np.where(swap, xb, xa), np.where(swap, xa, xb)
        ya, yb = np.where(swap, yb, ya), np.where(swap, ya, yb)
        dy = yb - ya
        with np.errstate(divide="ignore", invalid="ignore"):
            slope = np.where(dy > 0, (xb - xa) / np.where(dy > 0, dy, 1.0), 0.0)
        edges.append((xa, ya, yb, slope, dy > 0))

    # Row items: one per (triangle, pixel row).
    nrows = j1 - j0 + 1
    tri = np.repeat(np.arange(len(idx)), nrows)
    row = j0[tri] + (np.arange(len(tri)) - np.repeat(np.cumsum(nrows) - nrows, nrows))
    yc = row + 0.5
    xl = np.full(len(tri), np.inf)
    xr = np.full(len(tri), -np.inf)
    for xa, ya, yb, slope, ok in edges:
        xa, ya, yb, slope, ok = xa[tri], ya[tri], yb[tri], slope[tri], ok[tri]
        hit = ok & (yc >= ya) & (yc <= yb)
        xe = xa + (yc - ya) * slope
        xl = np.where(hit, np.minimum(xl, xe), xl)
        xr = np.where(hit, np.maximum(xr, xe), xr)
    good = xr >= xl
    i0 = np.maximum(np.ceil(np.where(good, xl, 0.0) - 0.5), 0).astype(np.int64)
    i1 = np.minimum(np.floor(np.where(good, xr, -1.0) - 0.5), W - 1).astype(np.int64)
    n = np.where(good, np.maximum(i1 - i0 + 1, 0), 0)
    sel = n > 0
    tri, row, i0, n = tri[sel], row[sel], i0[sel], n[sel]
    A, B, Cc = planes[tri, 0], planes[tri, 1], planes[tri, 2]
    inv0 = A * (i0 + 0.5) + B * (row + 0.5) + Cc  # inverse depth at span start
    base = row * W + i0
    face_of = idx[tri].astype(np.int32)

    zbuf = np.zeros(W * H)
    fbuf = np.full(W * H, -1, np.int32)
    ends = np.cumsum(n)
    start = 0
    while start < len(n):
        stop = int(np.searchsorted(ends, ends[start] - n[start] + _CHUNK, side="right"))
        stop = max(stop, start + 1)
        nn = n[start:stop]
        item = np.repeat(np.arange(start, stop), nn)
        k = np.arange(len(item)) - np.repeat(np.cumsum(nn) - nn, nn)
        pix = base[item] + k
        inv = inv0[item] + A[item] * k
        np.maximum.at(zbuf, pix, inv)
        win = inv >= zbuf[pix]
        fbuf[pix[win]] = face_of[item[win]]
        start = stop
    return Raster(zbuf.reshape(H, W), fbuf.reshape(H, W), all_planes)


def _final_pixel_rays(camera: Camera) -> np.ndarray:
    """(H, W, 2) normalised undistorted coordinates of the output pixel centres."""
    W, H = camera.width, camera.height
    jj, ii = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    xy = np.stack([jj.ravel(), ii.ravel()], 1)
    return camera.cam_from_img(xy).reshape(H, W, 2)


def make_canvas(
    camera: Camera, s: int, rays: np.ndarray | None = None
) -> tuple[Canvas, int, int]:
    """Canvas covering the (distorted) image at ``s`` x its resolution.

    Returns the canvas and its offsets (ox, oy) in canvas pixels (multiples of
    ``s``): canvas = s * undistorted_output_px - (ox, oy).
    """
    fx, fy, cx, cy = camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]
    if not camera.has_distortion:
        return (
            Canvas(s * fx, s * fy, s * cx, s * cy, s * camera.width, s * camera.height),
            0,
            0,
        )
    assert rays is not None
    u = fx * rays[..., 0] + cx
    v = fy * rays[..., 1] + cy
    ox = int(np.floor(np.nanmin(u) - 2)) * s
    oy = int(np.floor(np.nanmin(v) - 2)) * s
    w = int(np.ceil(np.nanmax(u) + 2)) * s - ox
    h = int(np.ceil(np.nanmax(v) + 2)) * s - oy
    return Canvas(s * fx, s * fy, s * cx - ox, s * cy - oy, w, h), ox, oy


def _canvas_points(
    pose: Pose, canvas: Canvas, inv_depth: np.ndarray, rows: slice
) -> np.ndarray:
    """(h, W, 3) float32 local-frame points of the canvas pixels of ``rows``.

    ``P = C + z R^T (x_n, y_n, 1)``; the ray is separable in rows and columns.
    """
    Rt = pose.rotation.astype(np.float32)  # rows: camera axes in the world
    xn = ((np.arange(canvas.width) + 0.5 - canvas.cx) / canvas.fx).astype(np.float32)
    yn = ((np.arange(rows.start, rows.stop) + 0.5 - canvas.cy) / canvas.fy).astype(
        np.float32
    )
    ray = xn[None, :, None] * Rt[0] + (yn[:, None] * Rt[1][None, :])[:, None, :] + Rt[2]
    z = (1.0 / inv_depth[rows]).astype(np.float32)
    return pose.center.astype(np.float32) + z[..., None] * ray


def final_buffers(
    city: City,
    camera: Camera,
    pose: Pose,
    canvas: Canvas,
    raster: Raster,
    rays: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """Depth (camera z, m; inf = nothing) and face id at the exact output pixel centres.

    The face is looked up in the canvas pixel containing the centre; the
    depth is that face's plane intersected with the exact pixel ray.
    """
    u = canvas.fx * rays[..., 0] + canvas.cx
    v = canvas.fy * rays[..., 1] + canvas.cy
    ju = np.clip(np.floor(u).astype(np.int64), 0, canvas.width - 1)
    iv = np.clip(np.floor(v).astype(np.int64), 0, canvas.height - 1)
    fid = raster.face_id[iv, ju]
    depth = np.full(fid.shape, np.inf, np.float32)
    m = fid >= 0
    pl = raster.planes[fid[m]]
    inv = pl[:, 0] * u[m] + pl[:, 1] * v[m] + pl[:, 2]
    fallback = raster.inv_depth[iv[m], ju[m]]
    inv = np.where(inv > 0.25 * fallback, inv, fallback)
    depth[m] = (1.0 / inv).astype(np.float32)
    return depth, fid


def _check_local(pose: Pose) -> None:
    if np.abs(pose.center).max() > 1e5:
        raise ValueError(
            f"camera centre {pose.center.round(1).tolist()} looks absolute; the city "
            "is in its LOCAL frame: use SyntheticScene.camera_pose or "
            "Block.shifted(city.origin)"
        )


def render_depth(
    city: City, camera: Camera, pose: Pose
) -> tuple[np.ndarray, np.ndarray]:
    """Only the z-buffer at output resolution: (depth (H, W) float32, face_id (H, W)).

    Depth is camera z in metres at the exact pixel centres (inf = nothing);
    pose in the LOCAL frame of the city.
    """
    _check_local(pose)
    rays = _final_pixel_rays(camera)
    canvas, _, _ = make_canvas(camera, 1, rays)
    raster = rasterize(city, pose, canvas)
    return final_buffers(city, camera, pose, canvas, raster, rays)


def render_image(
    city: City,
    camera: Camera,
    pose: Pose,
    options: SceneOptions,
    rng: np.random.Generator | None = None,
):
    """Render one image of the city.

    Parameters
    ----------
    city : City (local frame).
    camera : true intrinsics (COLMAP model; distortion is applied).
    pose : cam_from_world in the LOCAL frame of the city.
    options : rendering fields (supersample, blur, noise, sun, vignetting).
    rng : for the sensor noise; None gives a noise-free image.

    Returns
    -------
    image : (H, W, 3) uint8 RGB.
    depth : (H, W) float32 camera z in metres at the pixel centres, inf where
        nothing is seen.
    buffers : dict with ``face_id`` (H, W) int32 (-1 = nothing), ``surface_id``
        (H, W) int32, ``material`` (H, W) int8 (-1 = nothing) and ``timing_s``
        {"raster", "shade", "post"} in seconds.
    """
    _check_local(pose)
    s = int(options.supersample)
    W, H = camera.width, camera.height
    t0 = time.perf_counter()
    rays = _final_pixel_rays(camera)
    canvas, ox, oy = make_canvas(camera, s, rays)
    raster = rasterize(city, pose, canvas)
    depth, fid = final_buffers(city, camera, pose, canvas, raster, rays)
    t1 = time.perf_counter()

    # Shade the canvas in bands of rows (memory).
    sun = sun_direction(options.sun_azimuth_deg, options.sun_elevation_deg)
    img = np.empty((canvas.height, canvas.width, 3), np.float32)
    img[:] = np.array([0.55, 0.65, 0.8], np.float32)  # sky, never seen in practice
    band = max(1, 1_500_000 // canvas.width)
    for r0 in range(0, canvas.height, band):
        rows = slice(r0, min(r0 + band, canvas.height))
        f = raster.face_id[rows].ravel()
        m = f >= 0
        if not m.any():
            continue
        with np.errstate(divide="ignore", invalid="ignore"):
            P = _canvas_points(pose, canvas, raster.inv_depth, rows).reshape(-1, 3)[m]
        block = img[rows].reshape(-1, 3)
        block[m] = shade(city, P, f[m], sun)
        img[rows] = block.reshape(rows.stop - rows.start, canvas.width, 3)
    t2 = time.perf_counter()

    # Anti-aliasing box filter to the undistorted output grid.
    hc, wc = canvas.height // s, canvas.width // s
    small = img[: hc * s, : wc * s]
    if s > 1:  # INTER_AREA at an integer factor is the exact s x s box mean
        small = cv2.resize(small, (wc, hc), interpolation=cv2.INTER_AREA)
    if camera.has_distortion:
        fx, fy, cx, cy = camera.K[0, 0], camera.K[1, 1], camera.K[0, 2], camera.K[1, 2]
        # Undistorted output-resolution canvas: px = f x_n + c - offset / s;
        # cv2.remap indexes pixel centres at integers, hence -0.5.
        map_x = (fx * rays[..., 0] + cx - ox / s - 0.5).astype(np.float32)
        map_y = (fy * rays[..., 1] + cy - oy / s - 0.5).astype(np.float32)
        small = cv2.remap(
            small, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
        )
    out = small
    if options.vignetting > 0:
        jj, ii = np.meshgrid(
            (np.arange(W) + 0.5 - W / 2) / (W / 2),
            (np.arange(H) + 0.5 - H / 2) / (W / 2),
        )
        out = out * (
            1.0
            - options.vignetting * (jj**2 + ii**2) / (1 + 1 / options.image_aspect**2)
        )[..., None].astype(np.float32)
    if options.blur_sigma_px > 0:
        out = cv2.GaussianBlur(out, (0, 0), options.blur_sigma_px)
    out = out * 255.0
    if rng is not None and options.noise_sigma > 0:
        out = out + rng.normal(0.0, options.noise_sigma, out.shape).astype(np.float32)
    image = np.clip(np.rint(out), 0, 255).astype(np.uint8)
    t3 = time.perf_counter()
    surf = np.where(fid >= 0, city.face_surface[np.maximum(fid, 0)], -1).astype(
        np.int32
    )
    mat = np.where(fid >= 0, city.surf_material[np.maximum(surf, 0)], -1).astype(
        np.int8
    )
    buffers = {
        "face_id": fid,
        "surface_id": surf,
        "material": mat,
        "timing_s": {"raster": t1 - t0, "shade": t2 - t1, "post": t3 - t2},
    }
    return image, depth, buffers
