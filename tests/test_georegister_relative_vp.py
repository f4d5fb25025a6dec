"""Relative orientation from VPs (issue 27 item 5, MetropoGIS 3.2.2) against
known cameras: the horizontal VPs, the rotation from matched VP directions,
the 2-point position with the rotation known, and the refusals.

Scene: a street corner in a z-up world (down = -z): a facade in the plane
y = 15 (its horizontal lines along x) and a side wall in the plane x = 6
(lines along y), vertical edges on both, seen by a level-ish camera 1.6 m
up. Segments are projected exactly and their endpoints moved by Gaussian
noise of ``sigma_px`` across and along.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from obliq_colmap.geometry import rotation_angle_deg, rotation_z
from obliq_colmap.georegister.relative_vp import (
    RelativeVPOptions,
    centre_from_rotation,
    horizontal_vps,
    place_with_rotations,
    pool_directions,
    rotation_candidates,
)

F_PX, W, H = 1200.0, 1536, 1024
K = np.array([[F_PX, 0, W / 2], [0, F_PX, H / 2], [0, 0, 1.0]])
DOWN_WORLD = np.array([0.0, 0.0, -1.0])
#: the world's horizontal facade directions (as a neighbour's VPs give them)
H_WORLD = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])


def _camera(heading_deg: float, tilt_deg: float, centre) -> np.ndarray:
    """(3, 4) cam_from_world of a camera looking along +y (heading turns it
    about the vertical), pitched up by ``tilt_deg``."""
    # camera x right = world +x, y down = world -z, z forward = world +y
    R0 = np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]])
    t = np.radians(tilt_deg)
    pitch = np.array([[1, 0, 0], [0, np.cos(t), np.sin(t)], [0, -np.sin(t), np.cos(t)]])
    R = pitch @ R0 @ rotation_z(np.radians(heading_deg)).T
    return np.column_stack([R, -R @ np.asarray(centre, float)])


def _project(P: np.ndarray, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    Xc = X @ P[:, :3].T + P[:, 3]
    uv = Xc[:, :2] / Xc[:, 2:3] * F_PX + K[:2, 2]
    return uv, Xc[:, 2]


def _segments(P, rng, sigma_px, n_each=40, clutter=0):
    """(N, 2, 2) noisy segments of the scene's lines inside the image (and
    ``clutter`` random segments); the truth's (N,) labels: 0 vertical,
    1 along x, 2 along y, -1 clutter."""
    lines, labels = [], []
    for _ in range(n_each):
        # facade y = 15: horizontal along x, vertical
        x0, z0 = rng.uniform(-7, 3), rng.uniform(0.5, 6)
        lines.append([[x0, 15, z0], [x0 + rng.uniform(1, 3), 15, z0]])
        labels.append(1)
        lines.append([[x0, 15, z0], [x0, 15, z0 + rng.uniform(0.5, 2)]])
        labels.append(0)
        # side wall x = 6: horizontal along y
        y0, z1 = rng.uniform(6, 12), rng.uniform(0.5, 6)
        lines.append([[6, y0, z1], [6, y0 + rng.uniform(1, 2.5), z1]])
        labels.append(2)
    X = np.array(lines).reshape(-1, 3)
    uv, z = _project(P, X)
    seg = uv.reshape(-1, 2, 2)
    ok = (z.reshape(-1, 2) > 0).all(1)
    ok &= (seg >= 0).all((1, 2)) & (seg[..., 0] < W).all(1) & (seg[..., 1] < H).all(1)
    seg, labels = seg[ok], np.array(labels)[ok]
    if clutter:
        a = rng.uniform([0, 0], [W, H], (clutter, 2))
        ang = rng.uniform(0, np.pi, clutter)
        b = a + rng.uniform(40, 150, (clutter, 1)) * np.c_[np.cos(ang), np.sin(ang)]
        seg = np.concatenate([seg, np.stack([a, b], 1)])
        labels = np.concatenate([labels, -np.ones(clutter, int)])
    return seg + rng.normal(0, sigma_px, seg.shape), labels, seg


def _heading_error_deg(P_true, down_cam, hv) -> float:
    """The smallest angle between the truth's rotation and the candidates
    from the found horizontal VPs against the world's directions."""
    C = rotation_candidates(down_cam, hv.directions, DOWN_WORLD, H_WORLD)
    return float(np.min(rotation_angle_deg(C, P_true[:, :3][None])))


def _heading_sd_deg(seg, h_cam, down_cam, sigma_px) -> float:
    """First-order sd (deg) of the heading that :func:`horizontal_vps`'s fit
    gives from the (N, 2, 2) segments of one VP with i.i.d. endpoint noise
    sigma_px: the fit minimises sum w_j r_j^2 with r_j = n_j . h(theta),
    w_j = L_j^2, so var(theta) = sum w^2 g^2 var(r) / (sum w g^2)^2 with
    g_j = n_j . dh/dtheta and var(r_j) from the derivatives of r_j in the
    four endpoint coordinates (central differences)."""
    Kinv = np.linalg.inv(K)

    def residual(s):
        p = np.concatenate([s, np.ones(s.shape[:2] + (1,))], 2) @ Kinv.T
        n = np.cross(p[:, 0], p[:, 1])
        return (n / np.linalg.norm(n, axis=1, keepdims=True)) @ h_cam, n

    r0, n = residual(seg)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    g = n @ np.cross(down_cam, h_cam)
    var_r = np.zeros(len(seg))
    eps = 1e-4
    for a in range(2):
        for b in range(2):
            d = np.zeros_like(seg)
            d[:, a, b] = eps
            var_r += ((residual(seg + d)[0] - residual(seg - d)[0]) / (2 * eps)) ** 2
    var_r *= sigma_px**2
    w = np.linalg.norm(seg[:, 1] - seg[:, 0], axis=1) ** 2
    var = np.sum(w**2 * g**2 * var_r) / np.sum(w * g**2) ** 2
    return float(np.degrees(np.sqrt(var)))


def _best_family_sd_deg(P, seg_true, labels, sigma_px) -> float:
    """The smaller predicted heading sd of the two facade directions (the
    candidate nearest the truth comes from the better of them)."""
    down_cam = P[:, :3] @ DOWN_WORLD
    sds = [
        _heading_sd_deg(
            seg_true[labels == k + 1], P[:, :3] @ H_WORLD[k], down_cam, sigma_px
        )  # fmt: skip
        for k in range(2)
        if (labels == k + 1).sum() >= 12
    ]
    return min(sds)


def test_horizontal_vps_exact_without_noise():
    rng = np.random.default_rng(1)
    P = _camera(-15.0, 4.0, [0.0, 0.0, 1.6])
    seg, labels, seg_true = _segments(P, rng, 0.0)
    down_cam = P[:, :3] @ DOWN_WORLD
    hv = horizontal_vps(seg, K, down_cam, RelativeVPOptions(), exclude=labels == 0)
    assert len(hv.directions) == 2
    # both facade directions found, each with only its own segments (all
    # but those within 3 deg of the horizon line, which every horizontal VP
    # lies on)
    truth_cam = H_WORLD @ P[:, :3].T  # rows: R h
    for d, mask in zip(hv.directions, hv.inliers, strict=True):
        k = int(np.argmax(np.abs(truth_cam @ d)))
        assert abs(truth_cam[k] @ d) > 1 - 1e-12
        assert (labels[mask] == k + 1).all()
        assert mask.sum() >= 0.8 * (labels == k + 1).sum()
    assert _heading_error_deg(P, down_cam, hv) < 1e-6
    # perpendicular to the vertical by construction
    assert np.abs(hv.directions @ down_cam).max() < 1e-12


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rotation_from_vps_within_noise(seed):
    """With 0.5 px endpoint noise and clutter, the rotation candidate nearest
    the truth is within 4 sd (first order, :func:`_heading_sd_deg`) of the
    heading."""
    rng = np.random.default_rng(seed)
    sigma = 0.5
    P = _camera(rng.uniform(-30, -5), rng.uniform(-5, 10), [rng.uniform(-3, 1), 0, 1.6])
    seg, labels, seg_true = _segments(P, rng, sigma, clutter=60)
    down_cam = P[:, :3] @ DOWN_WORLD
    hv = horizontal_vps(seg, K, down_cam, RelativeVPOptions(), exclude=labels == 0)
    assert len(hv.directions) >= 1
    bound = 4.0 * _best_family_sd_deg(P, seg_true, labels, sigma)
    err = _heading_error_deg(P, down_cam, hv)
    assert err < bound, (err, bound)
    # the clutter did not join a facade's pencil in any number
    for mask in hv.inliers:
        assert (labels[mask] == -1).sum() <= 0.1 * mask.sum()


def test_rotation_candidates_are_rotations_and_hold_the_truth():
    P = _camera(30.0, 5.0, [0, 0, 1.6])
    R = P[:, :3]
    h_cam = H_WORLD @ R.T
    C = rotation_candidates(R @ DOWN_WORLD, h_cam, DOWN_WORLD, H_WORLD)
    assert C.shape == (2 * 2 * 2, 3, 3)
    np.testing.assert_allclose(
        C @ C.transpose(0, 2, 1), np.broadcast_to(np.eye(3), C.shape), atol=1e-12
    )
    np.testing.assert_allclose(np.linalg.det(C), 1.0)
    ang = rotation_angle_deg(C, R[None])
    assert np.min(ang) < 1e-6
    # all take the world's down to the camera's
    np.testing.assert_allclose(
        C @ DOWN_WORLD, np.broadcast_to(R @ DOWN_WORLD, (8, 3)), atol=1e-12
    )
    # the others turn about the vertical by multiples of 90 deg
    assert np.allclose(np.sort(ang)[1:] % 90.0, 0.0, atol=1e-6) or np.allclose(
        np.sort(ang)[1:] % 90.0, 90.0, atol=1e-6
    )


def _points(P, rng, n, sigma_px, outliers=0):
    """n facade points seen by P: (n, 3) world, (n, 3) rays (z = 1) with
    sigma_px noise; ``outliers`` of the rays replaced by random ones."""
    X = np.column_stack(
        [rng.uniform(-7, 5, n), rng.uniform(14, 16, n), rng.uniform(0, 7, n)]
    )
    uv, z = _project(P, X)
    keep = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < W) & (uv[:, 1] >= 0) & (uv[:, 1] < H)
    X, uv = X[keep], uv[keep]
    uv = uv + rng.normal(0, sigma_px, uv.shape)
    bad = rng.choice(len(X), outliers, replace=False)
    uv[bad] = rng.uniform([0, 0], [W, H], (outliers, 2))
    rays = np.column_stack([(uv - K[:2, 2]) / F_PX, np.ones(len(uv))])
    return X, rays, bad


def test_position_exact_without_noise():
    rng = np.random.default_rng(3)
    P = _camera(20.0, 3.0, [1.0, 0.5, 1.6])
    X, rays, _ = _points(P, rng, 30, 0.0)
    c, inl = centre_from_rotation(P[:, :3], rays, X, F_PX, RelativeVPOptions())
    assert inl.all()
    np.testing.assert_allclose(c, -P[:, :3].T @ P[:, 3], atol=1e-9)


def _centre_covariance(P, X, sigma_px) -> np.ndarray:
    """(3, 3) first-order covariance of the centre from the pixels of the
    (N, 3) points X with i.i.d. noise sigma_px, the rotation known:
    sigma^2 (sum J^T J)^-1, J the 2 x 3 derivative of the projection in c."""
    R = P[:, :3]
    Xc = X @ R.T + P[:, 3]
    x, y, z = Xc.T
    # d(f (x/z, y/z)) / dXc, then dXc/dc = -R
    J = np.zeros((len(X), 2, 3))
    J[:, 0, 0], J[:, 0, 2] = F_PX / z, -F_PX * x / z**2
    J[:, 1, 1], J[:, 1, 2] = F_PX / z, -F_PX * y / z**2
    J = -J @ R
    return sigma_px**2 * np.linalg.inv(np.einsum("nai,naj->ij", J, J))


#: chi-square with 3 degrees of freedom, 99.9 %
CHI2_3_999 = 16.27


@pytest.mark.parametrize(("seed", "score_points"), [(0, 1000), (1, 1000), (2, 15)])
def test_position_within_noise_and_outliers(seed, score_points):
    """1 px noise, 15 % outliers, rotation exact: the centre's error within
    the 99.9 % ellipsoid of its first-order covariance from the inliers
    (also with the hypotheses scored on 15 of the correspondences)."""
    rng = np.random.default_rng(seed)
    sigma = 1.0
    P = _camera(rng.uniform(-20, 20), 2.0, [rng.uniform(-2, 2), 0, 1.6])
    X, rays, bad = _points(P, rng, 60, sigma, outliers=9)
    opts = RelativeVPOptions(max_score_points=score_points)
    c, inl = centre_from_rotation(P[:, :3], rays, X, F_PX, opts)
    assert c is not None
    # the outliers are out (a random pixel can land within 4 px: rarely)
    assert inl[bad].sum() <= 1 and (~inl).sum() <= len(bad) + 1
    good = np.setdiff1d(np.arange(len(X)), bad)
    e = c - (-P[:, :3].T @ P[:, 3])
    cov = _centre_covariance(P, X[good], sigma)
    assert e @ np.linalg.solve(cov, e) < CHI2_3_999


def test_vp_rotation_and_position_together():
    """The whole geometric chain: horizontal VPs of a noisy image, the
    candidates within 60 deg of a neighbour's rotation (turned 20 deg from
    this one), the position picking among them: the true rotation and
    centre within their noise bounds."""
    rng = np.random.default_rng(5)
    P = _camera(-10.0, 3.0, [0.5, 0.0, 1.6])
    neighbour = _camera(10.0, 2.0, [-3.0, 0.0, 1.6])
    seg, labels, seg_true = _segments(P, rng, 0.5, clutter=40)
    down_cam = P[:, :3] @ DOWN_WORLD
    opts = RelativeVPOptions()
    hv = horizontal_vps(seg, K, down_cam, opts, exclude=labels == 0)
    C = rotation_candidates(down_cam, hv.directions, DOWN_WORLD, H_WORLD)
    X, rays, _ = _points(P, rng, 40, 0.5, outliers=5)
    k, c, inl, tried = place_with_rotations(C, neighbour[:, :3], rays, X, F_PX, opts)
    assert k >= 0 and tried >= 1
    rot_err = float(rotation_angle_deg(C[k], P[:, :3]))
    assert rot_err < 4.0 * _best_family_sd_deg(P, seg_true, labels, 0.5)
    # a rotation error e moves the centre by up to e * depth, on top of the
    # pixel noise's own (4 sd of the covariance's longest axis)
    depth = np.max((X @ P[:, :3].T + P[:, 3])[:, 2])
    sd_max = np.sqrt(np.linalg.eigvalsh(_centre_covariance(P, X[inl], 0.5)).max())
    bound = np.radians(rot_err) * depth + 4.0 * sd_max
    assert np.linalg.norm(c - (-P[:, :3].T @ P[:, 3])) < bound


def test_refuses_without_horizontal_structure():
    """Only vertical edges and clutter: no horizontal VP at all."""
    rng = np.random.default_rng(2)
    P = _camera(-15.0, 3.0, [0, 0, 1.6])
    seg, labels, seg_true = _segments(P, rng, 0.5, clutter=80)
    keep = labels <= 0
    hv = horizontal_vps(
        seg[keep],
        K,
        P[:, :3] @ DOWN_WORLD,
        RelativeVPOptions(),
        exclude=labels[keep] == 0,
    )
    assert len(hv.directions) == 0


def test_refuses_without_matches():
    """Too few correspondences, or only wrong ones: no position."""
    rng = np.random.default_rng(4)
    P = _camera(0.0, 0.0, [0, 0, 1.6])
    opts = RelativeVPOptions()
    X, rays, _ = _points(P, rng, 5, 0.5)
    c, _ = centre_from_rotation(P[:, :3], rays[:5], X[:5], F_PX, opts)
    assert c is None  # 5 < min_inliers
    X, rays, _ = _points(P, rng, 40, 0.5)
    rays_wrong = rays[rng.permutation(len(rays))]
    c, inl = centre_from_rotation(P[:, :3], rays_wrong, X, F_PX, opts)
    assert c is None and inl.sum() < opts.min_inliers
    # 8 right of 40 or more (> min_inliers, < a quarter): refused as well;
    # the same 8 alone are placed
    X, rays, _ = _points(P, rng, 60, 0.5)
    n = len(X)
    assert n >= 40
    mixed = np.concatenate([rays[:8], rays[8:][rng.permutation(n - 8)]])
    c, inl = centre_from_rotation(P[:, :3], mixed, X, F_PX, opts)
    assert c is None and inl[:8].all() and inl.sum() < 0.25 * n
    c, inl = centre_from_rotation(P[:, :3], rays[:8], X[:8], F_PX, opts)
    assert c is not None and inl.all()
    # and no candidate within reach of the reference: nothing tried
    C = rotation_candidates(P[:, :3] @ DOWN_WORLD, H_WORLD[:1] @ P[:, :3].T,
                            DOWN_WORLD, H_WORLD[:1])  # fmt: skip
    far = _camera(180.0, 0.0, [0, 0, 1.6])[:, :3] @ rotation_z(np.radians(90)).T
    k, c, _, tried = place_with_rotations(
        C, far, rays, X, F_PX, RelativeVPOptions(max_rotation_from_reference_deg=30)
    )
    assert k == -1 and c is None


def test_pool_directions_is_a_sign_free_mean_within_tolerance():
    down = np.array([0.0, 0.0, -1.0])

    def d(deg):
        return np.array([np.cos(np.radians(deg)), np.sin(np.radians(deg)), 0.0])

    # members at 10.2 and 190.6 (= 10.6, the other sign), weights 1 and 3;
    # 12 deg is beyond the 1 deg tolerance and must not count
    pool = np.array([d(10.2), d(190.6), d(12.0)])
    got = pool_directions(d(10.0)[None], pool, np.array([1.0, 3.0, 5.0]), down, 1.0)
    ang = np.degrees(np.arctan2(got[0, 1], got[0, 0]))
    # the axial mean: the doubled angles' weighted resultant, halved
    z = np.exp(2j * np.radians(10.2)) + 3 * np.exp(2j * np.radians(10.6))
    assert abs(ang - np.degrees(np.angle(z)) / 2) < 1e-9
    # with nothing near, the direction is kept
    kept = pool_directions(d(50.0)[None], pool, np.ones(3), down, 1.0)
    np.testing.assert_allclose(kept[0], d(50.0), atol=1e-12)


# --------------------------------------------------------------------------
# The stage on a model: which images are missing, writing one, refusals
# --------------------------------------------------------------------------


def _model_of_two(tmp_path):
    """A model of two registered images (im0, im1) with 20 points seen by
    both, and an image folder holding them, a third (im2) and a text file."""
    import cv2
    import pycolmap

    rec = pycolmap.Reconstruction()
    cam = pycolmap.Camera(model="PINHOLE", width=W, height=H,
                          params=[F_PX, F_PX, W / 2, H / 2])  # fmt: skip
    cam.camera_id = 1
    rec.add_camera_with_trivial_rig(cam)
    rng = np.random.default_rng(0)
    Ps = [_camera(-5.0, 2.0, [x, 0, 1.6]) for x in (-1.0, 1.0)]
    X, _, _ = _points(Ps[0], rng, 20, 0.0)
    for i, P in enumerate(Ps):
        im = pycolmap.Image(name=f"im{i}.png", camera_id=1, image_id=i + 1)
        uv, _ = _project(P, X)
        im.points2D = pycolmap.Point2DList([pycolmap.Point2D(u) for u in uv])
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(P[:, :3]), P[:, 3])
        rec.add_image_with_trivial_frame(im, pose)
    for k, Xk in enumerate(X):
        track = pycolmap.Track()
        track.add_element(1, k)
        track.add_element(2, k)
        rec.add_point3D(Xk, track, np.zeros(3, np.uint8))
    folder = tmp_path / "images"
    folder.mkdir()
    for n in ("im0.png", "im1.png"):
        cv2.imwrite(str(folder / n), np.zeros((H, W), np.uint8))
    cv2.imwrite(str(folder / "im2.png"), np.zeros((40, 60), np.uint8))
    (folder / "notes.txt").write_text("not an image")
    return rec, folder, Ps, X


def test_missing_images_and_write_placed(tmp_path):
    from obliq_colmap.georegister.relative_vp import (
        PlacedImage,
        missing_images,
        write_placed,
    )

    rec, folder, Ps, X = _model_of_two(tmp_path)
    assert missing_images(rec, folder) == ["im2.png"]
    P = _camera(0.0, 2.0, [0.0, -1.0, 1.6])
    uv, _ = _project(P, X[:8])
    ids = np.array(sorted(rec.points3D))[:8]
    placed = PlacedImage(
        "im2.png", "placed", "", cam_from_world=P, camera_id=1, points2D=uv,
        point3D_ids=ids,
    )  # fmt: skip
    image_id = write_placed(rec, placed)
    im = rec.images[image_id]
    assert im.name == "im2.png" and im.has_pose
    np.testing.assert_allclose(im.cam_from_world().matrix(), P, atol=1e-12)
    # its keypoints observe the model's points: they reproject exactly
    for p2 in im.points2D:
        Xw = rec.points3D[p2.point3D_id].xyz
        proj = im.camera.img_from_cam((im.cam_from_world() * Xw)[None])[0]
        np.testing.assert_allclose(proj, p2.xy, atol=1e-9)
    assert missing_images(rec, folder) == []


def test_place_image_refuses_an_image_of_no_camera(tmp_path):
    """im2 is 60 x 40 px, the model's camera 1536 x 1024: refused with a
    message that says so (no exception)."""
    from obliq_colmap.georegister.relative_vp import place_image

    rec, folder, _, _ = _model_of_two(tmp_path)
    placed = place_image(rec, folder, "im2.png", DOWN_WORLD, RelativeVPOptions())
    assert placed.status == "unreadable"
    assert "no camera of the model is 60 x 40 px" in placed.message
    assert placed.cam_from_world is None


def test_place_image_refuses_a_blank_image(tmp_path):
    """A blank image of the right size has no vertical VP: refused."""
    import cv2

    from obliq_colmap.georegister.relative_vp import place_image

    rec, folder, _, _ = _model_of_two(tmp_path)
    cv2.imwrite(str(folder / "im3.png"), np.full((H, W), 128, np.uint8))
    placed = place_image(rec, folder, "im3.png", DOWN_WORLD, RelativeVPOptions())
    assert placed.status == "no_vertical_vp" and placed.cam_from_world is None


HERZJESU = Path("/work/shared/data/strecha_herzjesu_p8_halfres")


@pytest.mark.slow
@pytest.mark.skipif(not HERZJESU.is_dir(), reason="Herz-Jesu-P8 not in ../shared")
def test_herzjesu_image_placed_from_its_neighbours(tmp_path):
    """A model of Herz-Jesu's TRUE cameras 0002 and 0004 whose points are
    their SIFT matches triangulated with those cameras; 0003 is missing and
    is placed by ``add_missing_images``. Its rotation comes from its VPs and
    the neighbours' (one image's horizontal VP heading scatters by 0.1-0.3
    deg on these images with true poses: 0.6 deg is 2-3 sd of two of them),
    its centre from the matches (1.8 cm in the bench with 2,700 of them; a
    rotation error e moves it by e x 15 m, 0.16 m at 0.6 deg)."""
    import os

    import pycolmap

    from obliq_colmap.georegister.relative_vp import (
        add_missing_images,
        read_gray,
        sift,
        verified_matches,
    )

    gt = pycolmap.Reconstruction(str(HERZJESU / "gt_colmap_halfres_text"))
    by_name = {gt.images[i].name: gt.images[i] for i in gt.reg_image_ids()}
    folder = tmp_path / "images"
    folder.mkdir()
    for n in ("0002.jpg", "0003.jpg", "0004.jpg"):
        os.symlink(HERZJESU / "images" / n, folder / n)
    a, b = by_name["0002.jpg"], by_name["0004.jpg"]
    cam = a.camera
    # the model's points from 4,096 keypoints per image (a subset of the
    # default 8,192's, which add_missing_images extracts): 7 s of matching
    # instead of 80 s
    fa, fb = (
        sift(read_gray(folder / n), max_num_features=4096)
        for n in ("0002.jpg", "0004.jpg")
    )
    m = verified_matches(fa, fb, cam, cam)
    # the rays' midpoints with the true cameras: (M, 3)
    Xs = []
    for im, xy in ((a, fa.xy[m[:, 0]]), (b, fb.xy[m[:, 1]])):
        R = im.cam_from_world().rotation.matrix()
        rays = np.column_stack([cam.cam_from_img(xy), np.ones(len(xy))]) @ R
        Xs.append(
            (im.projection_center(), rays / np.linalg.norm(rays, axis=1)[:, None])
        )
    (ca, da), (cb, db) = Xs
    # closest points of the two rays: solve [da, -db] [s, t]^T = cb - ca
    A = np.stack([da, -db], 2)  # (M, 3, 2)
    AtA = np.einsum("mki,mkj->mij", A, A)
    Atb = np.einsum("mki,k->mi", A, cb - ca)
    s, t = np.linalg.solve(AtA, Atb[..., None])[..., 0].T
    X = 0.5 * (ca + s[:, None] * da + cb + t[:, None] * db)
    rec = pycolmap.Reconstruction()
    # the truth's cameras of 0002-0004 share one lens (one camera per image)
    cam = pycolmap.Camera(
        model=cam.model, width=cam.width, height=cam.height, params=cam.params
    )
    cam.camera_id = 1
    rec.add_camera_with_trivial_rig(cam)
    for image_id, (im, f, col) in enumerate(((a, fa, 0), (b, fb, 1)), start=1):
        new = pycolmap.Image(name=im.name, camera_id=1, image_id=image_id)
        new.points2D = pycolmap.Point2DList(
            [pycolmap.Point2D(xy) for xy in f.xy[m[:, col]]]
        )
        rec.add_image_with_trivial_frame(new, im.cam_from_world())
    for k in range(len(X)):
        track = pycolmap.Track()
        track.add_element(1, k)
        track.add_element(2, k)
        rec.add_point3D(X[k], track, np.zeros(3, np.uint8))
    # the truth's down: its z axis points down to within 0.3 deg (README)
    report = add_missing_images(
        rec, folder, np.array([0.0, 0.0, 1.0]), RelativeVPOptions(), progress=False
    )
    assert report["0003.jpg"]["status"] == "placed", report
    placed = next(rec.images[i] for i in rec.reg_image_ids()
                  if rec.images[i].name == "0003.jpg")  # fmt: skip
    truth = by_name["0003.jpg"]
    R_err = rotation_angle_deg(
        placed.cam_from_world().rotation.matrix(),
        truth.cam_from_world().rotation.matrix(),
    )
    c_err = np.linalg.norm(placed.projection_center() - truth.projection_center())
    assert R_err < 0.6, (R_err, c_err)
    assert c_err < 0.1 + np.radians(R_err) * 15.0, (R_err, c_err)
    assert placed.num_points3D >= 100
    print(f"0003: rotation {R_err:.3f} deg, centre {c_err:.3f} m")


def test_place_image_refuses_a_truncated_jpeg(tmp_path):
    """A JPEG cut short (it would decode with grey rows) is refused and
    the reason named."""
    import cv2

    from obliq_colmap.georegister.relative_vp import place_image

    rec, folder, _, _ = _model_of_two(tmp_path)
    ok, buf = cv2.imencode(".jpg", np.full((H, W), 90, np.uint8))
    (folder / "im4.jpg").write_bytes(buf.tobytes()[: len(buf) // 2])
    placed = place_image(rec, folder, "im4.jpg", DOWN_WORLD, RelativeVPOptions())
    assert placed.status == "unreadable" and "truncated JPEG" in placed.message
