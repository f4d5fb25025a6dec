"""Synthetic bundle problems with exact ground truth (tests and benchmark).

Box buildings on a jittered grid, standing on a smooth terrain, are seen by a
multi-head oblique camera (one COLMAP camera per head, 45 degrees off nadir)
from a grid of exposure stations. The constraints are exact at the truth:

* vertical: for every corner visible in an image (one of its two facades
  faces the camera, both ends in the image), the line through the projections
  of the corner's ground and roof points (distorted pixels);
* horizontal: for every facade facing the camera, at floor levels every 3 m,
  the line through the projections of the facade-edge centre at that height
  and of a point 3 m along the edge, if that line crosses the projected
  vertical at more than ``min_line_angle_deg``; a level is kept when seen in
  >= 2 images.

Noise shifts a line by a Gaussian amount: perpendicular for vertical lines,
along the projected vertical for horizontal ones, so that both residual kinds
get exactly ``noise_px`` of noise. Outliers shift lines by 10-50 px.

This is independent of the rendering scene generator of this package
(:mod:`obliq_colmap.synthetic.city` and its renderer): no images, only the
bundle's constraints; occlusion is ignored.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from obliq_colmap.bundle import BundleProblem
from obliq_colmap.bundle import residuals as res
from obliq_colmap.geometry import (
    Camera,
    Pose,
    lines_through,
    rotation_from_axis_angle,
)

__all__ = ["PAPER_FLIGHT", "SyntheticBundle", "concatenate", "make_synthetic_problem"]

#: The `paper` preset's camera and flight at full size (4008 x 2672 px,
#: 6000 px focal, 500 m, 40 m building spacing, 300 m between stations),
#: the setting of the bundle benchmarks; the block's size (``buildings``,
#: ``stations``) is each caller's.
PAPER_FLIGHT = dict(
    spacing_m=40.0,
    station_spacing_m=300.0,
    altitude_m=500.0,
    width=4008,
    height=2672,
    focal_px=6000.0,
    noise_px=0.5,
    corner_height_start_sigma_m=2.0,
)


@dataclass
class SyntheticBundle:
    """A perturbed problem and its truth.

    Attributes
    ----------
    problem : BundleProblem, the perturbed start with noisy constraints.
    cameras, poses : the true intrinsics and ``cam_from_world``.
    facade_heights : (J,) true heights h_j, metres.
    corner_heights : (C,) true corner ground heights, metres.
    vertical_outlier, horizontal_outlier : (M,), (H,) bool masks.
    tie_xyz : (T, 3) true tie points (the problem's ``tie_xyz`` is the start).
    """

    problem: BundleProblem
    cameras: dict[int, Camera]
    poses: dict[int, Pose]
    facade_heights: np.ndarray
    corner_heights: np.ndarray
    vertical_outlier: np.ndarray
    horizontal_outlier: np.ndarray
    tie_xyz: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))


def _terrain(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return 0.02 * x - 0.01 * y + 3.0 * np.sin(x / 150.0) * np.cos(y / 210.0)


def _head_rotation(
    heading_deg: float, tilt_deg: float, jitter: np.ndarray
) -> np.ndarray:
    """cam_from_world of a head looking at ``heading`` (clockwise from north)."""
    psi, th = np.radians(heading_deg), np.radians(tilt_deg)
    fwd = np.array([np.sin(psi) * np.sin(th), np.cos(psi) * np.sin(th), -np.cos(th)])
    right = np.array([np.cos(psi), -np.sin(psi), 0.0])
    down = np.cross(fwd, right)
    R = np.stack([right, down, fwd])
    return rotation_from_axis_angle(jitter) @ R


def _in_cone(pts: np.ndarray, pose: Pose, cos_cone: float) -> np.ndarray:
    """(N,) bool: the (N, 3) points within the cone of cosine ``cos_cone``
    around the camera's viewing axis."""
    ray = pts - pose.center
    along = ray @ pose.rotation[2]
    return along > cos_cone * np.linalg.norm(ray, axis=1)


def make_synthetic_problem(
    *,
    seed: int = 0,
    buildings: tuple[int, int] = (6, 6),
    spacing_m: float = 40.0,
    stations: tuple[int, int] = (2, 2),
    station_spacing_m: float = 150.0,
    altitude_m: float = 300.0,
    tilt_deg: float = 45.0,
    models: tuple[str, ...] = ("SIMPLE_RADIAL",) * 4,
    width: int = 2000,
    height: int = 1400,
    focal_px: float = 3000.0,
    floor_spacing_m: float = 3.0,
    noise_px: float = 0.0,
    outlier_fraction: float = 0.0,
    rotation_error_deg: float = 0.5,
    center_error_m: float = 5.0,
    focal_error: float = 0.02,
    height_start_sigma_m: float = 2.0,
    corner_height_start_sigma_m: float = 0.0,
    min_line_angle_deg: float = 30.0,
    keep_vertical_datum: bool = True,
    image_id_offset: int = 0,
    camera_id_offset: int = 0,
    origin_xy: tuple[float, float] = (0.0, 0.0),
    view_cone_margin_deg: float | None = None,
    tie_points: int = 0,
    tie_noise_px: float | None = None,
    end_noise_px: float | None = None,
) -> SyntheticBundle:
    """Build a synthetic bundle problem (see the module docstring).

    The exposure stations form a ``stations`` grid centred on the building
    block, with one image per head (``len(models)`` heads at headings 0, 90,
    180, 270 degrees). The start is the truth perturbed by a rotation of
    ``rotation_error_deg`` about a random axis, a centre shift of
    ``center_error_m`` in a random direction and focal lengths scaled by
    ``1 +- focal_error``; start heights get Gaussian noise. With
    ``keep_vertical_datum`` the centre shifts have zero mean height, so the
    solver's gauge (mean camera height of the start) is the true datum and
    the truth is the exact optimum of a noise-free problem.

    ``view_cone_margin_deg`` (e.g. 10): project only the points within this
    angle outside the image's field of view (its half diagonal), which makes
    large blocks (``stations`` of hundreds) fast to build; None: every point.

    ``tie_points``: so many points on the terrain, uniform over the block,
    observed (with ``tie_noise_px`` of Gaussian noise per axis, default
    ``noise_px``) in every image they fall in (occlusion ignored) and kept
    where seen at least twice; their start is the truth 1 m off per axis.

    Every horizontal observation also carries its segment's two ends
    (``horizontal_ends``: the projections of the edge centre and of a point
    3 m along the edge, on the observed line) and each track its map edge's
    direction (``facade_direction``), for the facade lines. With
    ``end_noise_px`` the ends are the projections of the points 40 % of the
    wall's length either side of its centre (clipping ignored), each moved
    across by its own Gaussian noise (drawn after everything else), and the
    observed line is the line through them.
    """
    rng = np.random.default_rng(seed)
    ox, oy = origin_xy
    # --- buildings: (B, 4, 2) footprints, counter-clockwise
    gx, gy = np.meshgrid(
        np.arange(buildings[0]), np.arange(buildings[1]), indexing="ij"
    )
    centres = np.stack([gx.ravel(), gy.ravel()], 1) * spacing_m
    centres = centres - centres.mean(0) + (ox, oy)
    centres += rng.uniform(-0.1, 0.1, centres.shape) * spacing_m
    B = len(centres)
    half = rng.uniform(5.0, 0.35 * spacing_m, (B, 2))
    yaw = rng.uniform(0, np.pi / 2, B)
    sq = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]], float)
    c, s = np.cos(yaw), np.sin(yaw)
    Rb = np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)  # (B, 2, 2)
    foot = centres[:, None, :] + np.einsum("bij,bkj->bki", Rb, sq[None] * half[:, None])
    ground = _terrain(foot[..., 0], foot[..., 1]).min(1)  # (B,)
    bheight = rng.uniform(6.0, 40.0, B)
    corner_xy = foot.reshape(-1, 2)
    corner_ground = np.repeat(ground, 4)
    corner_roof = corner_ground + np.repeat(bheight, 4)

    # --- cameras and poses
    heads = [0.0, 90.0, 180.0, 270.0][: len(models)]
    cameras = {}
    for h, model in enumerate(models):
        f = focal_px * (1 + rng.uniform(-0.03, 0.03))
        cx = width / 2 + rng.uniform(-8, 8)
        cy = height / 2 + rng.uniform(-8, 8)
        extra = {
            "SIMPLE_PINHOLE": [f, cx, cy],
            "PINHOLE": [f, f * 1.001, cx, cy],
            "SIMPLE_RADIAL": [f, cx, cy, -0.03],
            "RADIAL": [f, cx, cy, -0.03, 0.01],
            "OPENCV": [f, f * 1.001, cx, cy, -0.03, 0.01, 2e-4, -1e-4],
        }[model]
        cid = camera_id_offset + h + 1
        cameras[cid] = Camera(model, width, height, np.array(extra), cid)
    sx, sy = np.meshgrid(np.arange(stations[0]), np.arange(stations[1]), indexing="ij")
    st_xy = np.stack([sx.ravel(), sy.ravel()], 1) * station_spacing_m
    st_xy = st_xy - st_xy.mean(0) + (ox, oy)
    poses, image_camera, image_ids = {}, {}, []
    for si, (x, y) in enumerate(st_xy):
        for h, heading in enumerate(heads):
            # Aim each head at the block: step back from the station.
            psi = np.radians(heading)
            back = altitude_m * np.tan(np.radians(tilt_deg)) * 0.8
            C = np.array(
                [
                    x - back * np.sin(psi),
                    y - back * np.cos(psi),
                    altitude_m + rng.uniform(-5, 5),
                ]
            )
            R = _head_rotation(
                heading, tilt_deg + rng.uniform(-2, 2), rng.normal(0, 0.01, 3)
            )
            iid = image_id_offset + si * len(heads) + h + 1
            poses[iid] = Pose.from_center(R, C)
            image_camera[iid] = camera_id_offset + h + 1
            image_ids.append(iid)
    K = len(image_ids)

    def project(k: int, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        pose = poses[image_ids[k]]
        cam = cameras[image_camera[image_ids[k]]]
        Xc = pose.transform(pts)
        ok = Xc[:, 2] > 1.0
        xy = np.full((len(pts), 2), np.nan)
        xy[ok] = res.project(cam.model, cam.params, Xc[ok])
        inside = (
            ok
            & (xy[:, 0] > 5)
            & (xy[:, 0] < width - 5)
            & (xy[:, 1] > 5)
            & (xy[:, 1] < height - 5)
        )
        return xy, inside

    # --- facades: edge e of building b from corner e to e + 1
    a = foot
    bnext = np.roll(foot, -1, axis=1)
    edge_mid = 0.5 * (a + bnext).reshape(-1, 2)  # (4B, 2)
    edge_dir = (bnext - a).reshape(-1, 2)
    edge_dir /= np.linalg.norm(edge_dir, axis=1, keepdims=True)
    outward = np.stack([edge_dir[:, 1], -edge_dir[:, 0]], 1)  # CCW polygon
    e_ground, e_height = np.repeat(ground, 4), np.repeat(bheight, 4)

    # facade heights: floor levels
    lv_edge, lv_z = [], []
    for e in range(len(edge_mid)):
        z = e_ground[e] + 1.5 + np.arange(0.0, e_height[e] - 2.0, floor_spacing_m)
        lv_edge.append(np.full(len(z), e))
        lv_z.append(z)
    lv_edge, lv_z = np.concatenate(lv_edge), np.concatenate(lv_z)
    lv_xy = edge_mid[lv_edge]
    lv_pts = np.column_stack([lv_xy, lv_z])
    lv_pts2 = np.column_stack([lv_xy + 3.0 * edge_dir[lv_edge], lv_z])
    # a segment over 80 % of the wall, for the noisy ends
    half_len = 0.4 * np.linalg.norm(bnext - a, axis=2).ravel()[lv_edge]
    lv_a = np.column_stack([lv_xy - half_len[:, None] * edge_dir[lv_edge], lv_z])
    lv_b = np.column_stack([lv_xy + half_len[:, None] * edge_dir[lv_edge], lv_z])

    h_img, h_lv, h_line, h_ends = [], [], [], []
    v_img, v_corner, v_line = [], [], []
    g_pts = np.column_stack([corner_xy, corner_ground])
    r_pts = np.column_stack([corner_xy, corner_roof])
    # With a margin, only points inside a cone around each image's axis are
    # projected (the image's half diagonal + the margin), so a block of
    # thousands of images builds in linear time. It also leaves out the rare
    # points far outside the view whose distorted projection folds back into
    # the image (the radial polynomial turns over near 70 deg off-axis).
    cos_cone = -1.0  # no cone: every point in front of the camera
    if view_cone_margin_deg is not None:
        half_diag = np.arctan(0.5 * np.hypot(width, height) / focal_px)
        cone = half_diag + np.radians(view_cone_margin_deg)
        cos_cone = float(np.cos(min(cone, np.pi)))
    for k in range(K):
        pose = poses[image_ids[k]]
        cam = cameras[image_camera[image_ids[k]]]
        C = pose.center
        # facades facing the camera, not grazing
        to_cam = C[None, :2] - edge_mid
        view = np.column_stack([to_cam, np.full(len(edge_mid), C[2])])
        view /= np.linalg.norm(view, axis=1, keepdims=True)
        facing = np.einsum("ni,ni->n", outward, view[:, :2]) > 0.25
        sel = np.flatnonzero(facing[lv_edge] & _in_cone(lv_pts, pose, cos_cone))
        p1, in1 = project(k, lv_pts[sel])
        p2, in2 = project(k, lv_pts2[sel])
        m = in1 & in2
        # Horizontal lines must cross the projected vertical at a good angle.
        _, J, _ = res.project_with_jacobian(
            cam.model, cam.params, pose.transform(lv_pts[sel])
        )
        d = np.einsum("nij,j->ni", J, pose.rotation[:, 2])
        t = p2 - p1
        sin = np.abs(t[:, 0] * d[:, 1] - t[:, 1] * d[:, 0]) / (
            np.linalg.norm(t, axis=1) * np.linalg.norm(d, axis=1)
        )
        m &= np.nan_to_num(sin) > np.sin(np.radians(min_line_angle_deg))
        h_img.append(np.full(m.sum(), k))
        h_lv.append(sel[m])
        h_line.append(lines_through(p1[m], p2[m]))
        if end_noise_px:
            pa, _ = project(k, lv_a[sel][m])  # clipping ignored
            pb, _ = project(k, lv_b[sel][m])
            h_ends.append(np.stack([pa, pb], axis=1))
        else:
            h_ends.append(np.stack([p1[m], p2[m]], axis=1))
        # corners: either adjacent facade faces the camera
        cf = facing.reshape(B, 4)
        corner_vis = (cf | np.roll(cf, 1, axis=1)).ravel()
        sel = np.flatnonzero(
            corner_vis
            & _in_cone(g_pts, pose, cos_cone)
            & _in_cone(r_pts, pose, cos_cone)
        )
        q1, i1 = project(k, g_pts[sel])
        q2, i2 = project(k, r_pts[sel])
        m = i1 & i2
        v_img.append(np.full(m.sum(), k))
        v_corner.append(sel[m])
        v_line.append(lines_through(q1[m], q2[m]))
    h_img, h_lv, h_line, h_ends = map(np.concatenate, (h_img, h_lv, h_line, h_ends))
    v_img, v_corner, v_line = map(np.concatenate, (v_img, v_corner, v_line))
    # keep levels seen in >= 2 images; re-index
    cnt = np.bincount(h_lv, minlength=len(lv_z))
    keep_lv = np.flatnonzero(cnt >= 2)
    new_index = np.full(len(lv_z), -1)
    new_index[keep_lv] = np.arange(len(keep_lv))
    m = cnt[h_lv] >= 2
    h_img, h_height, h_line = h_img[m], new_index[h_lv[m]], h_line[m]
    h_ends = h_ends[m]
    facade_direction = edge_dir[lv_edge[keep_lv]]
    anchor = lv_xy[h_lv[m]]
    facade_true = lv_z[keep_lv]

    # --- noise and outliers
    def vertical_dir(k_idx, pts):
        out = np.zeros((len(pts), 2))
        for k in np.unique(k_idx):
            sel = k_idx == k
            pose = poses[image_ids[k]]
            cam = cameras[image_camera[image_ids[k]]]
            Xc = pose.transform(pts[sel])
            _, J, _ = res.project_with_jacobian(cam.model, cam.params, Xc)
            d = np.einsum("nij,j->ni", J, pose.rotation[:, 2])
            out[sel] = d / np.linalg.norm(d, axis=1, keepdims=True)
        return out

    if noise_px > 0:
        v_line[:, 2] += rng.normal(0, noise_px, len(v_line))
        dh = vertical_dir(h_img, np.column_stack([anchor, facade_true[h_height]]))
        cos = np.abs(np.einsum("ni,ni->n", h_line[:, :2], dh))
        h_line[:, 2] += rng.normal(0, noise_px, len(h_line)) * cos
    v_out = rng.random(len(v_line)) < outlier_fraction
    h_out = rng.random(len(h_line)) < outlier_fraction
    for L, o in ((v_line, v_out), (h_line, h_out)):
        L[o, 2] += rng.choice([-1, 1], o.sum()) * rng.uniform(10, 50, o.sum())

    # the segments' ends on the observed (noisy) lines
    nrm = h_line[:, :2] / np.linalg.norm(h_line[:, :2], axis=1, keepdims=True)
    if not end_noise_px:
        off = h_line[:, 2] / np.linalg.norm(h_line[:, :2], axis=1)
        dist = np.einsum("nki,ni->nk", h_ends, nrm) + off[:, None]
        h_ends = h_ends - dist[..., None] * nrm[:, None, :]

    # --- tie points on the terrain
    t_noise = noise_px if tie_noise_px is None else tie_noise_px
    t_xyz, t_img, t_pt, t_xy = np.zeros((0, 3)), [], [], []
    if tie_points:
        lo, hi = corner_xy.min(0) - spacing_m, corner_xy.max(0) + spacing_m
        xy = rng.uniform(lo, hi, (tie_points, 2))
        pts = np.column_stack([xy, _terrain(xy[:, 0], xy[:, 1])])
        for k in range(K):
            q, inside = project(k, pts)
            t_img.append(np.full(inside.sum(), k))
            t_pt.append(np.flatnonzero(inside))
            t_xy.append(q[inside] + rng.normal(0, t_noise, (inside.sum(), 2)))
        t_img, t_pt, t_xy = map(np.concatenate, (t_img, t_pt, t_xy))
        seen = np.bincount(t_pt, minlength=tie_points) >= 2
        keep = seen[t_pt]
        _, t_pt = np.unique(t_pt[keep], return_inverse=True)
        t_img, t_xy = t_img[keep], t_xy[keep]
        t_xyz = pts[seen]
    t_true = t_xyz.copy()

    # --- perturbed start
    start_poses = {}
    shifts = rng.normal(size=(K, 3))
    shifts *= center_error_m / np.linalg.norm(shifts, axis=1, keepdims=True)
    if keep_vertical_datum:
        shifts[:, 2] -= shifts[:, 2].mean()
    for k, (iid, pose) in enumerate(poses.items()):
        axis = rng.normal(size=3)
        axis *= np.radians(rotation_error_deg) / np.linalg.norm(axis)
        start_poses[iid] = Pose.from_center(
            rotation_from_axis_angle(axis) @ pose.rotation, pose.center + shifts[k]
        )
    start_cams = {}
    for cid, cam in cameras.items():
        p = cam.params.copy()
        focal, _, _ = res.focal_principal_extra_indices(cam.model)
        p[focal] *= 1 + rng.choice([-1, 1]) * focal_error
        start_cams[cid] = Camera(cam.model, cam.width, cam.height, p, cid)
    # (the start draws in this order: the random stream of earlier problems)
    corner_start = (
        corner_ground
        + rng.normal(0, 1, len(corner_ground)) * corner_height_start_sigma_m
    )
    facade_start = (
        facade_true + rng.normal(0, 1, len(facade_true)) * height_start_sigma_m
    )
    tie_start = t_xyz + rng.normal(0, 1.0, t_xyz.shape)
    if end_noise_px:
        h_ends = (
            h_ends
            + rng.normal(0, end_noise_px, (len(h_ends), 2))[..., None] * nrm[:, None, :]
        )
        h_line = lines_through(h_ends[:, 0], h_ends[:, 1])
    problem = BundleProblem(
        cameras=start_cams,
        poses=start_poses,
        image_camera=image_camera,
        image_ids=tuple(image_ids),
        corner_xy=corner_xy,
        corner_heights=corner_start,
        vertical_image=v_img,
        vertical_corner=v_corner,
        vertical_line=v_line,
        facade_heights=facade_start,
        horizontal_image=h_img,
        horizontal_height=h_height,
        horizontal_anchor_xy=anchor,
        horizontal_line=h_line,
        horizontal_ends=h_ends,
        facade_direction=facade_direction,
        tie_xyz=tie_start,
        tie_image=np.asarray(t_img, np.int64),
        tie_point=np.asarray(t_pt, np.int64),
        tie_xy=np.asarray(t_xy, float).reshape(-1, 2),
    )
    return SyntheticBundle(
        problem, cameras, poses, facade_true, corner_ground, v_out, h_out, t_true
    )


def concatenate(a: SyntheticBundle, b: SyntheticBundle) -> SyntheticBundle:
    """Two independent synthetic problems as one (ids must not collide)."""
    pa, pb = a.problem, b.problem
    if set(pa.poses) & set(pb.poses) or set(pa.cameras) & set(pb.cameras):
        raise ValueError("image or camera ids collide; use the id offsets")
    ka, ca, ja = len(pa.image_ids), len(pa.corner_xy), len(pa.facade_heights)
    cat = np.concatenate
    problem = BundleProblem(
        cameras={**pa.cameras, **pb.cameras},
        poses={**pa.poses, **pb.poses},
        image_camera={**pa.image_camera, **pb.image_camera},
        image_ids=pa.image_ids + pb.image_ids,
        corner_xy=cat([pa.corner_xy, pb.corner_xy]),
        corner_heights=cat([pa.corner_heights, pb.corner_heights]),
        vertical_image=cat([pa.vertical_image, pb.vertical_image + ka]),
        vertical_corner=cat([pa.vertical_corner, pb.vertical_corner + ca]),
        vertical_line=cat([pa.vertical_line, pb.vertical_line]),
        facade_heights=cat([pa.facade_heights, pb.facade_heights]),
        horizontal_image=cat([pa.horizontal_image, pb.horizontal_image + ka]),
        horizontal_height=cat([pa.horizontal_height, pb.horizontal_height + ja]),
        horizontal_anchor_xy=cat([pa.horizontal_anchor_xy, pb.horizontal_anchor_xy]),
        horizontal_line=cat([pa.horizontal_line, pb.horizontal_line]),
        horizontal_ends=cat([pa.horizontal_ends, pb.horizontal_ends]),
        facade_direction=cat([pa.facade_direction, pb.facade_direction]),
        tie_xyz=cat([pa.tie_xyz, pb.tie_xyz]),
        tie_image=cat([pa.tie_image, pb.tie_image + ka]),
        tie_point=cat([pa.tie_point, pb.tie_point + len(pa.tie_xyz)]),
        tie_xy=cat([pa.tie_xy, pb.tie_xy]),
    )
    return replace(
        a,
        problem=problem,
        cameras={**a.cameras, **b.cameras},
        poses={**a.poses, **b.poses},
        facade_heights=cat([a.facade_heights, b.facade_heights]),
        corner_heights=cat([a.corner_heights, b.corner_heights]),
        vertical_outlier=cat([a.vertical_outlier, b.vertical_outlier]),
        horizontal_outlier=cat([a.horizontal_outlier, b.horizontal_outlier]),
        tie_xyz=cat([a.tie_xyz, b.tie_xyz]),
    )
