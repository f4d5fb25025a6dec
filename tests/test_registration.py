"""Initial registration (stage 2): minimal solver, RANSAC, refinement, the stage.

Tiers (EXAMPLES.md, section 7): exact synthetic correspondences recover the
pose to machine precision; outliers give exactly the true inlier set; noise
gives errors of the size of the noise; failures are values with a message.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from shapely import affinity
from shapely.geometry import box

from obliq_colmap.cadastre import load_cadastre, visible_corners, write_geojson
from obliq_colmap.geometry import (
    Camera,
    Pose,
    rotation_angle_deg,
    rotation_from_axis_angle,
    rotation_z,
)
from obliq_colmap.registration import (
    RegistrationOptions,
    consensus_peak,
    draw_registration_overlay,
    focal_profile,
    inlier_threshold_px,
    ransac_core,
    refine_with_camera,
    register_image,
)

ORIGIN = np.array([500_000.0, 5_600_000.0, 0.0])
TOL_EXACT_DEG = 1e-6
TOL_EXACT_M = 1e-4


# --------------------------------------------------------------------------
# Ground truth: a small city of boxes seen by one oblique camera
# --------------------------------------------------------------------------


def oblique_pose(center: np.ndarray, heading_deg: float, tilt_deg: float) -> Pose:
    """cam_from_world of a camera looking along ``heading`` (clockwise from north)."""
    psi, tilt = math.radians(heading_deg), math.radians(tilt_deg)
    d = np.array([math.sin(psi), math.cos(psi), 0.0])
    z = math.cos(tilt) * np.array([0.0, 0.0, -1.0]) + math.sin(tilt) * d
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return Pose.from_center(np.stack([x, y, z]), center)


def ground_z(xy: np.ndarray) -> np.ndarray:
    """The true terrain: a gentle plane (true vertical datum)."""
    return 0.01 * xy[:, 0] - 0.005 * xy[:, 1] + 3.0


@dataclasses.dataclass
class Block:
    cadastre: object
    camera: Camera
    pose: Pose
    segments: np.ndarray  # (N, 2, 2) undistorted pixels
    pairs: set  # {(corner, segment)} of the true segments
    heights: dict  # building index -> height (m)


def make_block(
    seed: int = 0,
    num_outliers: int = 150,
    shift_building: bool = False,
    tmp_path=None,
    heading_deg: float = 20.0,
) -> Block:
    rng = np.random.default_rng(seed)
    polys, props = [], []
    for gx in range(-6, 7):
        for gy in range(-6, 7):
            cx, cy = gx * 38.0 + rng.uniform(-4, 4), gy * 38.0 + rng.uniform(-4, 4)
            w, h = rng.uniform(12, 24, 2)
            p = affinity.rotate(
                box(cx - w / 2, cy - h / 2, cx + w / 2, cy + h / 2),
                17.0 + rng.uniform(-3, 3),
                origin=(cx, cy),
            )
            polys.append(affinity.translate(p, ORIGIN[0], ORIGIN[1]))
            props.append({"id": len(props), "height": float(rng.uniform(8, 30))})
    path = tmp_path / f"map_{seed}_{int(shift_building)}.geojson"
    write_geojson(path, polys, crs="EPSG:25832", properties=props)
    cadastre = load_cadastre(path, origin=ORIGIN)
    heights = dict(enumerate(cadastre.heights))
    camera = Camera("PINHOLE", 1000, 667, [1000.0, 1000.0, 500.0, 333.5])
    psi = math.radians(heading_deg)
    center = np.array([-250 * math.sin(psi), -250 * math.cos(psi), 253.0])
    pose = oblique_pose(center, heading_deg, 45.0)

    vis = visible_corners(cadastre, camera, pose, ground_z, (0.0, 60.0))
    xy = cadastre.corner_xy[vis]
    z0 = ground_z(xy)
    top = z0 + cadastre.heights[cadastre.corner_building[vis]]
    p0 = camera.img_from_cam(pose.transform(np.column_stack([xy, z0])))
    p1 = camera.img_from_cam(pose.transform(np.column_stack([xy, top])))
    W, H = camera.width, camera.height
    inside = np.all((p0 >= 0) & (p0 < [W, H]), axis=1) & np.all(np.isfinite(p1), axis=1)
    # Clip the tops to the image (the bottoms are inside).
    d = p1 - p0
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.ones(len(d))
        for k, lim in ((0, W), (1, H)):
            t = np.minimum(
                t,
                np.where(
                    d[:, k] > 0,
                    (lim - 1e-6 - p0[:, k]) / d[:, k],
                    np.where(d[:, k] < 0, -p0[:, k] / d[:, k], 1.0),
                ),
            )
    p1 = p0 + t[:, None] * d
    long_enough = np.linalg.norm(p1 - p0, axis=1) >= 15
    keep = inside & long_enough
    # Drop ambiguous corners: another corner's ground point inside the
    # inlier ellipse of this segment's bottom (even if it is not drawn).
    unit = d / np.linalg.norm(d, axis=1, keepdims=True)
    normal = np.column_stack([-unit[:, 1], unit[:, 0]])
    for i in np.flatnonzero(keep):
        q = p0 - p0[i]
        across = np.abs(q @ normal[i])
        along = np.abs(q @ unit[i])
        near = (across < 6) & (along < 40)
        near[i] = False
        if near[inside].any():
            keep[i] = False
    true_seg = np.stack([p0[keep], p1[keep]], axis=1)
    true_corner = vis[keep]
    # Outliers through the VP, away from every corner's ground point.
    vp = camera.K @ (pose.rotation @ np.array([0.0, 0.0, -1.0]))
    vp = vp[:2] / vp[2]
    outliers = []
    while len(outliers) < num_outliers:
        b = rng.uniform([0, 0], [W, H])
        u = (b - vp) / np.linalg.norm(b - vp)
        n_ = np.array([-u[1], u[0]])
        q = p0[inside] - b
        if np.any((np.abs(q @ n_) < 8) & (np.abs(q @ u) < 50)):
            continue
        outliers.append([b, b + u * rng.uniform(15, 80)])
    segments = np.concatenate([true_seg, np.asarray(outliers)])
    order = rng.permutation(len(segments))
    segments = segments[order]
    where = np.argsort(order)  # new index of each old segment
    pairs = {(int(c), int(where[k])) for k, c in enumerate(true_corner)}
    if shift_building:
        # The map (not the scene) shifts the building with most true pairs.
        b = np.bincount(cadastre.corner_building[true_corner]).argmax()
        polys[b] = affinity.translate(polys[b], 1.2, -0.9)
        path2 = tmp_path / f"map_{seed}_shifted.geojson"
        write_geojson(path2, polys, crs="EPSG:25832", properties=props)
        cadastre = load_cadastre(path2, origin=ORIGIN)
    return Block(cadastre, camera, pose, segments, pairs, heights)


def perturbed_prior(
    pose: Pose, seed: int, position_m=5.0, heading_deg=1.0, tilt_deg=0.5, datum_m=47.0
) -> Pose:
    rng = np.random.default_rng(seed + 100)
    c = pose.center + np.r_[rng.normal(0, position_m, 2), datum_m + rng.normal(0, 3)]
    R = pose.rotation @ rotation_z(math.radians(heading_deg))  # heading
    R = rotation_from_axis_angle([math.radians(tilt_deg), 0.0, 0.0]) @ R  # tilt
    return Pose.from_center(R, c)


def vertical_of(pose: Pose) -> np.ndarray:
    return pose.rotation @ np.array([0.0, 0.0, -1.0])


def assert_pose_close(result, pose: Pose, prior: Pose, rot_deg: float, centre_m: float):
    """Rotation and horizontal centre within tolerances; height held at the prior."""
    assert result.success, result.message
    est = result.cam_from_world
    assert rotation_angle_deg(est.rotation, pose.rotation) < rot_deg
    assert np.linalg.norm(est.center[:2] - pose.center[:2]) < centre_m
    assert est.center[2] == pytest.approx(prior.center[2], abs=1e-9)
    R = est.rotation
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


@pytest.fixture(scope="module")
def block(tmp_path_factory):
    return make_block(0, tmp_path=tmp_path_factory.mktemp("reg"))


# --------------------------------------------------------------------------
# Minimal solver
# --------------------------------------------------------------------------


def random_problem(rng, B: int):
    """B random oblique cameras, three corners each, exact lines through the VP."""
    K = np.array([[1200.0, 0, 500], [0, 1200.0, 330], [0, 0, 1]])
    data = []
    for _ in range(B):
        pose = oblique_pose(
            np.r_[rng.uniform(-50, 50, 2), rng.uniform(150, 400)],
            rng.uniform(0, 360),
            rng.uniform(30, 60),
        )
        R = pose.rotation
        n = R @ np.array([0.0, 0.0, -1.0])
        # R_vanish: R with an arbitrary extra rotation about the vertical.
        R0 = R @ rotation_z(rng.uniform(-np.pi, np.pi))
        alpha_true = np.arctan2((R0.T @ R)[1, 0], (R0.T @ R)[0, 0])
        ahead = pose.center[:2] + 300 * (R[2, :2] / np.linalg.norm(R[2, :2]))
        X = np.column_stack(
            [ahead + rng.uniform(-80, 80, (3, 2)), rng.uniform(-5, 30, 3)]
        )
        p = X @ R.T + pose.translation
        q = (X + [0, 0, 10.0]) @ R.T + pose.translation
        lines = np.cross(p @ K.T, q @ K.T)
        lines /= np.linalg.norm(lines[:, :2], axis=1, keepdims=True)
        m = lines @ K @ R0  # (R0^T K^T l)^T
        mid = 0.5 * (p / p[:, 2:] + q / q[:, 2:])  # normalised midpoints
        side = mid - (mid @ n)[:, None] * n
        data.append((m[:, :2], X[:, :2], side, R0, alpha_true, pose.center[:2], n))
    return data


def test_minimal_solver_exact_random_cameras():
    rng = np.random.default_rng(1)
    for m, xy, side, R0, alpha, c, _ in random_problem(rng, 50):
        ref = c + rng.uniform(-20, 20, 2)  # any reference point
        a, cxy, valid = ransac_core.solve_minimal(
            m[None], (xy - ref)[None], R0, side[None]
        )
        assert valid[0]
        assert abs(np.angle(np.exp(1j * (a[0] - alpha)))) < 1e-9
        np.testing.assert_allclose(cxy[0] + ref, c, atol=1e-7)


def test_minimal_solver_vectorised_matches_single():
    rng = np.random.default_rng(2)
    data = random_problem(rng, 20)
    # One shared R_vanish is needed for a batch: use one camera, many samples.
    m, xy, side, R0, alpha, c, n = data[0]
    rows_m = np.repeat(m[None], 1000, axis=0)
    rows_xy = np.repeat(xy[None], 1000, axis=0) - c
    rows_side = np.repeat(side[None], 1000, axis=0)
    a, cxy, valid = ransac_core.solve_minimal(rows_m, rows_xy, R0, rows_side)
    assert valid.all()
    np.testing.assert_allclose(a, alpha, atol=1e-9)
    np.testing.assert_allclose(cxy, 0.0, atol=1e-7)


def test_minimal_solver_two_signs_and_cheirality():
    rng = np.random.default_rng(3)
    m, xy, side, R0, alpha, c, _ = random_problem(rng, 1)[0]
    rows = ransac_core.constraint_rows(m, xy - c)[None]
    w, valid = ransac_core.null_vectors(rows)
    assert valid[0]
    np.testing.assert_allclose(rows[0] @ w[0], 0.0, atol=1e-9)
    assert w[0, 0] ** 2 + w[0, 1] ** 2 == pytest.approx(1.0)
    # Both signs solve the algebraic system with the same centre ...
    for sign in (1.0, -1.0):
        a, cxy = ransac_core.pose_parameters(sign * w)
        np.testing.assert_allclose(cxy[0], 0.0, atol=1e-7)
    # ... and cheirality keeps the true one, whatever sign came out.
    for sign in (1.0, -1.0):
        w2, ok = ransac_core.choose_sign(
            sign * w, valid, R0, (xy - c)[None], side[None]
        )
        a, _ = ransac_core.pose_parameters(w2)
        assert ok[0]
        assert abs(np.angle(np.exp(1j * (a[0] - alpha)))) < 1e-9
    # Segments on the wrong side for one pair only: inconsistent sample.
    bad = side.copy()
    bad[0] *= -1
    _, ok = ransac_core.choose_sign(w, valid, R0, (xy - c)[None], bad[None])
    assert not ok[0]


def test_minimal_solver_degenerate_samples():
    rng = np.random.default_rng(4)
    m, xy, side, R0, _, c, _ = random_problem(rng, 1)[0]
    m2, xy2 = m.copy(), xy.copy()
    m2[2], xy2[2] = m2[1], xy2[1]  # a repeated pair
    _, _, valid = ransac_core.solve_minimal(m2[None], (xy2 - c)[None], R0, side[None])
    assert not valid[0]
    with pytest.raises(ValueError, match="rows must be"):
        ransac_core.null_vectors(np.zeros((2, 4, 4)))


@pytest.mark.parametrize(
    ("inlier_ratio", "expected"),
    # Hartley & Zisserman, table 4.3 (p = 0.99, s = 3).
    [(0.95, 3), (0.9, 4), (0.8, 7), (0.75, 9), (0.7, 11), (0.6, 19), (0.5, 35)],
)
def test_required_trials_textbook(inlier_ratio, expected):
    assert ransac_core.required_trials(inlier_ratio, 3, 0.99) == expected


def test_required_trials_paper_and_limits():
    # The paper: ~6.5 % inliers need about 20k samples of 3.
    assert 15_000 < ransac_core.required_trials(0.065, 3, 0.99) < 20_000
    assert ransac_core.required_trials(0.0) == math.inf
    assert ransac_core.required_trials(1.0) == 1
    with pytest.raises(ValueError):
        ransac_core.required_trials(0.5, 3, 1.0)


def test_sample_pairs_distinct_and_deterministic():
    corner = np.array([0, 0, 1, 2, 3, 3, 4])
    segment = np.array([0, 1, 1, 2, 3, 4, 5])
    a = ransac_core.sample_pairs(np.random.default_rng(5), 500, corner, segment)
    b = ransac_core.sample_pairs(np.random.default_rng(5), 500, corner, segment)
    np.testing.assert_array_equal(a, b)
    assert len(a) > 0
    for s in a:
        assert len(set(corner[s])) == 3 and len(set(segment[s])) == 3


# --------------------------------------------------------------------------
# The stage on exact synthetic correspondences
# --------------------------------------------------------------------------


def test_register_exact_with_outliers_recovers_pose_and_inlier_set(block):
    prior = perturbed_prior(block.pose, 0)
    assert len(block.pairs) >= 30
    result = register_image(
        block.segments,
        vertical_of(block.pose),
        block.camera,
        prior,
        block.cadastre,
        segments_undistorted=True,
    )
    assert_pose_close(result, block.pose, prior, TOL_EXACT_DEG, TOL_EXACT_M)
    assert {tuple(p) for p in result.inlier_pairs.tolist()} == block.pairs
    assert result.num_inliers == len(block.pairs)
    assert result.residual_rms_px < 1e-6
    # The height plane is the terrain in the prior's datum (c_z shifted).
    dz = prior.center[2] - block.pose.center[2]
    a, b, c = result.height_plane
    np.testing.assert_allclose([a, b, c], [0.01, -0.005, 3.0 + dz], atol=1e-5)
    assert result.ground_height == pytest.approx(3.0 + dz, abs=15.0)
    assert result.num_candidates >= result.num_inliers
    assert result.num_trials > 0 and 0 < result.inlier_ratio <= 1
    assert set(result.timings) >= {"ground", "coarse", "ransac", "refine", "total"}


def test_register_deterministic_for_a_seed(block):
    prior = perturbed_prior(block.pose, 1)
    n = vertical_of(block.pose)
    opts = RegistrationOptions(seed=3)
    r1 = register_image(
        block.segments,
        n,
        block.camera,
        prior,
        block.cadastre,
        opts,
        segments_undistorted=True,
    )
    r2 = register_image(
        block.segments,
        n,
        block.camera,
        prior,
        block.cadastre,
        opts,
        segments_undistorted=True,
    )
    np.testing.assert_array_equal(
        r1.cam_from_world.matrix(), r2.cam_from_world.matrix()
    )
    np.testing.assert_array_equal(r1.inlier_pairs, r2.inlier_pairs)
    assert r1.num_trials == r2.num_trials


def test_register_with_noise_matches_noise(block):
    rng = np.random.default_rng(7)
    sigma = 0.3
    noisy = block.segments + rng.normal(0, sigma, block.segments.shape)
    prior = perturbed_prior(block.pose, 2)
    result = register_image(
        noisy,
        vertical_of(block.pose),
        block.camera,
        prior,
        block.cadastre,
        segments_undistorted=True,
    )
    assert_pose_close(result, block.pose, prior, 0.05, 0.6)
    # Residuals of the size of the endpoint noise: too small would be a bug.
    assert 0.5 * sigma < result.residual_rms_px < 1.5 * sigma
    found = {tuple(p) for p in result.inlier_pairs.tolist()}
    assert len(found & block.pairs) >= 0.9 * len(block.pairs)
    assert len(found - block.pairs) <= 2


def test_register_ignores_a_shifted_building(tmp_path):
    blk = make_block(1, shift_building=True, tmp_path=tmp_path)
    prior = perturbed_prior(blk.pose, 3)
    result = register_image(
        blk.segments,
        vertical_of(blk.pose),
        blk.camera,
        prior,
        blk.cadastre,
        segments_undistorted=True,
    )
    assert_pose_close(result, blk.pose, prior, TOL_EXACT_DEG, TOL_EXACT_M)
    b = np.bincount(blk.cadastre.corner_building[[c for c, _ in blk.pairs]]).argmax()
    inlier_buildings = blk.cadastre.corner_building[result.inlier_pairs[:, 0]]
    assert b not in set(inlier_buildings.tolist())


def test_register_large_prior_error(block):
    prior = perturbed_prior(block.pose, 4, position_m=20.0, heading_deg=3.0)
    opts = RegistrationOptions(
        prior_position_sigma_m=20.0,
        prior_rotation_sigma_deg=3.0,
        num_candidates_verified=16,
    )
    result = register_image(
        block.segments,
        vertical_of(block.pose),
        block.camera,
        prior,
        block.cadastre,
        opts,
        segments_undistorted=True,
    )
    assert_pose_close(result, block.pose, prior, TOL_EXACT_DEG, TOL_EXACT_M)


def test_register_without_vp_uses_and_refines_the_prior_vertical(block):
    prior = perturbed_prior(block.pose, 5, tilt_deg=0.4)
    result = register_image(
        block.segments,
        None,
        block.camera,
        prior,
        block.cadastre,
        segments_undistorted=True,
    )
    assert result.success, result.message
    assert result.vertical_source == "refined"
    assert (
        rotation_angle_deg(result.cam_from_world.rotation, block.pose.rotation) < 0.05
    )


def test_register_with_known_ground_height(block):
    prior = perturbed_prior(block.pose, 6)
    dz = prior.center[2] - block.pose.center[2]
    opts = RegistrationOptions(ground_height=3.0 + dz)
    result = register_image(
        block.segments,
        vertical_of(block.pose),
        block.camera,
        prior,
        block.cadastre,
        opts,
        segments_undistorted=True,
    )
    assert_pose_close(result, block.pose, prior, TOL_EXACT_DEG, TOL_EXACT_M)


def test_known_ground_height_verifies_more_poses_than_heights(block):
    """A weak image with a given ground height (the rescue's and the
    re-registration's case): the ground band has only a few height cells, so
    the strongest pose of each leaves 2-3 starts, and a weak image's true
    pose need not be the strongest coarse cell of its height (chance
    alignments of clutter compete with it). The next strongest poses fill
    the starts up to ``num_candidates_verified``. 12 true segments among 60
    chance verticals: the true pose is found only with the extra starts."""

    true_segments = sorted({s for _, s in block.pairs})
    keep = np.random.default_rng(5).choice(true_segments, 12, replace=False)
    segments = np.concatenate(
        [block.segments[keep], _random_verticals(block, 60, seed=15)]
    )
    prior = perturbed_prior(block.pose, 9)
    dz = prior.center[2] - block.pose.center[2]
    args = (segments, vertical_of(block.pose), block.camera, prior, block.cadastre)
    opts = RegistrationOptions(ground_height=3.0 + dz, fill_starts_with_poses=True)
    result = register_image(*args, opts, segments_undistorted=True)
    assert_pose_close(result, block.pose, prior, 0.2, 1.0)
    assert result.num_inliers > opts.chance_factor * result.chance_inliers

    # One start per height (the default): the weak image is lost.
    plain = RegistrationOptions(ground_height=3.0 + dz)
    single = register_image(*args, plain, segments_undistorted=True)
    assert not single.success


def test_more_poses_fills_the_starts_without_repeats():
    from obliq_colmap.registration.hough import HoughPeak
    from obliq_colmap.registration.search import _more_poses

    def peak(a, h, v):
        return HoughPeak(a, np.array([a, -a]), h, v)

    starts = [peak(0.0, 1.0, 9.0), peak(0.1, 5.0, 7.0)]
    peaks = [peak(0.0, 1.0, 9.0), peak(0.2, 1.0, 8.0), peak(0.1, 5.0, 7.0)]
    peaks += [peak(0.3, 5.0, 6.0), peak(0.4, 1.0, 5.0)]
    more = _more_poses(peaks, starts, 4)
    assert [p.alpha for p in more] == [0.2, 0.3]
    assert _more_poses(peaks, starts, 2) == []


def test_register_distorted_segments_are_undistorted(block):
    cam = Camera("RADIAL", 1000, 667, [1000.0, 500.0, 333.5, -0.05, 0.01])
    seg = block.segments.reshape(-1, 2)
    uv = (seg - [500.0, 333.5]) / 1000.0
    distorted = cam.img_from_cam(np.column_stack([uv, np.ones(len(uv))]))
    prior = perturbed_prior(block.pose, 7)
    result = register_image(
        distorted.reshape(-1, 2, 2), vertical_of(block.pose), cam, prior, block.cadastre
    )
    assert_pose_close(result, block.pose, prior, 1e-5, 1e-3)


def _corner_px_per_k(camera: Camera) -> float:
    """Displacement (px) at the image corners per unit of radial k1."""
    f = camera.K[0, 0]
    return f * (0.5 * math.hypot(camera.width, camera.height) / f) ** 3


@pytest.mark.parametrize("model", ["SIMPLE_RADIAL", "RADIAL"])
def test_register_estimates_an_unknown_radial_distortion(block, model):
    """A lens the priors do not have (k1 = -0.08, 17 px at the corners): with
    ``refine_distortion`` (the default) the estimate agrees with the truth
    within the endpoint noise at the image corners; without, k1 stays 0 and
    the residuals stay well above the noise."""
    sigma = 0.3
    extra = [-0.08] if model == "SIMPLE_RADIAL" else [-0.08, 0.0]
    true = Camera(model, 1000, 667, [1000.0, 500.0, 333.5, *extra])
    uv = (block.segments.reshape(-1, 2) - [500.0, 333.5]) / 1000.0
    raw = true.img_from_cam(np.column_stack([uv, np.ones(len(uv))]))
    rng = np.random.default_rng(3)
    raw = raw.reshape(-1, 2, 2) + rng.normal(0, sigma, block.segments.shape)
    rough = Camera(model, 1000, 667, [1000.0, 500.0, 333.5] + [0.0] * len(extra))
    prior = perturbed_prior(block.pose, 7)
    kw = dict(segments_undistorted=False)
    held = RegistrationOptions(refine_distortion=False)
    fixed = register_image(
        raw, vertical_of(block.pose), rough, prior, block.cadastre, held, **kw
    )
    opts = RegistrationOptions()  # refine_distortion by default
    free = register_image(
        raw, vertical_of(block.pose), rough, prior, block.cadastre, opts, **kw
    )
    assert fixed.success and not fixed.distortion_refined
    assert fixed.camera.params[3] == 0.0
    assert fixed.residual_rms_px > 2.0 * sigma
    assert free.success and free.distortion_refined
    err_px = abs(free.camera.params[3] - extra[0]) * _corner_px_per_k(true)
    assert err_px < sigma, free.camera.params
    assert 0.5 * sigma < free.residual_rms_px < 1.5 * sigma
    # Looser in rotation than with a known lens (0.05 deg): k1 and the focal
    # length share the pitch's weak mode (a vertical VP 1 f below the frame).
    assert_pose_close(free, block.pose, prior, 0.15, 0.6)
    assert len(free.inlier_pairs) >= 0.9 * len(block.pairs)
    # The inlier segments come back in the input camera's frame (here, k1 = 0:
    # as given), not undistorted with the estimate.
    np.testing.assert_array_equal(free.inlier_segments_px, raw[free.inlier_pairs[:, 1]])


# --------------------------------------------------------------------------
# Failures are values
# --------------------------------------------------------------------------


def test_too_few_segments_fails_with_message(block):
    prior = perturbed_prior(block.pose, 8)
    result = register_image(
        block.segments[:3],
        vertical_of(block.pose),
        block.camera,
        prior,
        block.cadastre,
        segments_undistorted=True,
    )
    assert not result.success and not result
    assert "too few vertical segments" in result.message
    assert result.cam_from_world is prior


def test_no_consensus_fails_with_message(block):
    prior = perturbed_prior(block.pose, 9)
    rng = np.random.default_rng(0)
    junk = rng.uniform(0, 600, (40, 2, 2))  # not vertical at all
    junk[:, 1] = junk[:, 0] + [0.0, 40.0]
    result = register_image(
        junk,
        vertical_of(block.pose),
        block.camera,
        prior,
        block.cadastre,
        segments_undistorted=True,
    )
    assert not result.success
    assert "segments" in result.message or "consensus" in result.message


def _random_verticals(block, num: int, seed: int) -> np.ndarray:
    """(num, 2, 2) segments through the block's vertical VP at random places:
    valid verticals that match no map corner but by chance."""
    rng = np.random.default_rng(seed)
    vp = block.camera.K @ vertical_of(block.pose)
    vp = vp[:2] / vp[2]
    start = rng.uniform([0, 0], [block.camera.width, block.camera.height], (num, 2))
    unit = (vp - start) / np.linalg.norm(vp - start, axis=1, keepdims=True)
    length = rng.uniform(20.0, 120.0, num)
    return np.stack([start, start + length[:, None] * unit], axis=1)


@pytest.mark.slow
def test_chance_consensus_fails_and_a_true_one_passes(block):
    """Segments that match the map only by chance: the search alone still
    finds a consensus; the same search with the segments mirrored finds as
    many, so the result is refused. The true segments beat their chance
    count by far."""
    prior = perturbed_prior(block.pose, 9)
    junk = _random_verticals(block, 300, seed=4)
    args = (junk, vertical_of(block.pose), block.camera, prior, block.cadastre)
    untested = register_image(
        *args, RegistrationOptions(chance_trials=0), segments_undistorted=True
    )
    assert untested.success and untested.chance_inliers == -1
    tested = register_image(*args, segments_undistorted=True)
    assert not tested.success and tested.cam_from_world is prior
    assert "no more than chance" in tested.message
    assert tested.num_inliers == untested.num_inliers
    assert untested.num_inliers <= 1.5 * tested.chance_inliers

    always = RegistrationOptions(chance_test_below=10_000)
    true = register_image(
        block.segments,
        vertical_of(block.pose),
        block.camera,
        prior,
        block.cadastre,
        always,
        segments_undistorted=True,
    )
    assert true.success and true.chance_inliers >= 0
    assert true.num_inliers > 3 * true.chance_inliers
    assert "chance" in true.timings


def test_map_out_of_view_fails(block):
    far = Pose.from_center(block.pose.rotation, block.pose.center + [5000.0, 0, 0])
    result = register_image(
        block.segments,
        vertical_of(block.pose),
        block.camera,
        far,
        block.cadastre,
        segments_undistorted=True,
    )
    assert not result.success
    assert result.message


def test_near_nadir_view_fails_with_message(block):
    """A view 2 deg off nadir has its vertical VP inside the frame: the
    registration refuses it with a message (unless allowed); the oblique
    test block's VP lies below the frame and passes the check."""
    nadir = oblique_pose(block.pose.center, 0.0, 2.0)
    result = register_image(
        block.segments,
        vertical_of(nadir),
        block.camera,
        nadir,
        block.cadastre,
        segments_undistorted=True,
    )
    assert not result.success
    assert "near-nadir view" in result.message and "inside" in result.message
    allowed = register_image(
        block.segments,
        vertical_of(nadir),
        block.camera,
        nadir,
        block.cadastre,
        RegistrationOptions(allow_vp_in_frame=True),
        segments_undistorted=True,
    )
    assert "near-nadir" not in allowed.message
    oblique = register_image(
        block.segments,
        vertical_of(block.pose),
        block.camera,
        perturbed_prior(block.pose, 8),
        block.cadastre,
        segments_undistorted=True,
    )
    assert oblique.success


@pytest.mark.parametrize(
    ("segments", "n", "match"),
    [
        (np.zeros((5, 2)), None, "segments_px must be"),
        (np.zeros((5, 2, 2)), [0.0, 0.0, 0.0], "vertical_direction_cam"),
        (np.zeros((5, 2, 2)), [np.nan, 1.0, 0.0], "vertical_direction_cam"),
    ],
)
def test_bad_input_raises(block, segments, n, match):
    with pytest.raises(ValueError, match=match):
        register_image(segments, n, block.camera, block.pose, block.cadastre)


def test_inlier_threshold_follows_the_ground_sampling():
    """The map's vertex noise lives in metres: at twice the pixels per metre
    the inlier threshold doubles, down to the pixel threshold (edge noise)."""
    o = RegistrationOptions(inlier_threshold_px=2.0, inlier_threshold_m=0.3)
    assert inlier_threshold_px(o, 1 / 0.15) == pytest.approx(2.0)
    assert inlier_threshold_px(o, 1 / 0.075) == pytest.approx(4.0)
    assert inlier_threshold_px(o, 1 / 0.3) == pytest.approx(2.0)
    pixels_only = dataclasses.replace(o, inlier_threshold_m=0.0)
    assert inlier_threshold_px(pixels_only, 1 / 0.075) == pytest.approx(2.0)
    with pytest.raises(ValueError, match="inlier_threshold_m"):
        RegistrationOptions(inlier_threshold_m=-1.0)


def test_options_validate():
    with pytest.raises(ValueError, match="inlier_threshold_px"):
        RegistrationOptions(inlier_threshold_px=0.0)
    with pytest.raises(ValueError, match="refine_vertical"):
        RegistrationOptions(refine_vertical="sometimes")
    with pytest.raises(ValueError, match="confidence"):
        RegistrationOptions(confidence=1.0)
    with pytest.raises(TypeError):
        RegistrationOptions(0.5)  # keyword-only


def test_overlay_draws_before_and_after(block):
    prior = perturbed_prior(block.pose, 0)
    result = register_image(
        block.segments,
        vertical_of(block.pose),
        block.camera,
        prior,
        block.cadastre,
        segments_undistorted=True,
    )
    image = np.full((block.camera.height, block.camera.width), 128, np.uint8)
    out = draw_registration_overlay(image, block.cadastre, block.camera, prior, result)
    assert out.shape == (block.camera.height, block.camera.width, 3)
    assert out.dtype == np.uint8
    red = (out[..., 2] > 200) & (out[..., 1] < 100)
    green = (out[..., 1] > 200) & (out[..., 2] < 100)
    assert red.sum() > 500 and green.sum() > 500
    assert np.all(image == 128)  # input untouched


# --------------------------------------------------------------------------
# Vectorised internals against simple references
# --------------------------------------------------------------------------


def _small_problem(block, num_pairs: int = 40):
    """A view, its segments, corners and a few true and false pairs near the
    prior, for the accumulator tests."""
    from obliq_colmap.registration.segments import pairs_near, prepare_segments
    from obliq_colmap.registration.view import make_view

    prior = perturbed_prior(block.pose, 3, position_m=2.0, heading_deg=0.3)
    view = make_view(block.camera, prior, vertical_of(block.pose))
    segs = prepare_segments(block.segments, view, RegistrationOptions())
    corner_rel = block.cadastre.corner_xy - view.c0[:2]
    ii, jj = pairs_near(
        view, segs, corner_rel, 0.0, np.zeros(2), 40.0, h_range=(-100.0, 100.0)
    )
    pick = np.random.default_rng(0).choice(len(ii), num_pairs, replace=False)
    pick.sort()
    return view, segs, corner_rel, ii[pick], jj[pick]


def _hough_reference(view, segs, corner_rel, ii, jj, grid, heights: bool):
    """The pose vote by its definition, one vote at a time: for every alpha of
    the grid and every pair, walk the constraint line's cells along the axis
    on which it moves least, round the other coordinate, and (with heights)
    put the vote at the height of the segment's bottom on the corner's
    vertical, seen from the point of the line (in front of the ray only)."""
    from scipy.ndimage import uniform_filter

    na, n1, n2, nh = grid.acc.shape
    half = np.array([n1 // 2, n2 // 2])
    acc = np.zeros(grid.acc.shape)
    for ka, alpha in enumerate(grid.alphas):
        ca, sa = math.cos(alpha), math.sin(alpha)
        for i, j in zip(ii, jj, strict=True):
            mx, my = segs.m_xy[j]
            x, y = corner_rel[i] - grid.c_center
            rhs = (mx * x + my * y) * ca + (my * x - mx * y) * sa
            g = np.array([ca * mx + sa * my, -sa * mx + ca * my])
            a = np.array([g @ grid.axes[0], g @ grid.axes[1]]) * grid.steps
            it = 1 if abs(a[0]) >= abs(a[1]) else 0  # the axis walked
            ot = 1 - it
            for t in range(-half[it], half[it] + 1):
                other = (rhs - a[it] * t) / a[ot]
                k = np.zeros(2)
                k[it], k[ot] = t, round(other)
                if abs(k[ot]) > half[ot]:
                    continue
                ih = 0
                if heights:
                    kc = k.copy()
                    kc[ot] = other
                    c = grid.c_center + (kc * grid.steps) @ grid.axes
                    h = view.bottom_heights(
                        np.array([alpha]),
                        c[None],
                        corner_rel[i][None],
                        segs.bottom[j][None],
                    )[0, 0]
                    if not np.isfinite(h):
                        continue
                    ih = math.floor((h - grid.h_lo) / grid.d_h)
                    if not 0 <= ih < nh:
                        continue
                kk = (k + half).astype(int)
                acc[ka, kk[0], kk[1], ih] += min(segs.length[j], 60.0)
    acc = acc.astype(np.float32)
    return uniform_filter(acc, size=(3, 3, 3, min(nh, 3)), mode="constant")


@pytest.mark.parametrize("heights", [False, True])
def test_hough_matches_a_vote_by_vote_reference(block, heights):
    from obliq_colmap.registration.hough import hough

    view, segs, corner_rel, ii, jj = _small_problem(block)
    grid = hough(
        view,
        segs,
        corner_rel,
        ii,
        jj,
        0.0,
        0.01,
        np.zeros(2),
        4.0,
        (3.0, 6.0, 6.0),
        float(np.median(np.linalg.norm(corner_rel[ii], axis=1))),
        10**6,
        heights=(-30.0, 30.0, 2.0) if heights else None,
    )
    assert grid.acc.shape[0] >= 5 and grid.acc.shape[1] >= 5
    ref = _hough_reference(view, segs, corner_rel, ii, jj, grid, heights)
    assert ref.max() > 0
    # A vote in another cell would differ by a whole weight (>= 8 px / 27).
    np.testing.assert_allclose(grid.acc, ref, rtol=1e-5, atol=1e-3)


def test_rasterise_matches_enumeration_at_cell_boundaries():
    """Rows built to hit every rounding edge (half-integer other coordinates,
    heights exactly on the accumulator's bounds, a corner exactly on the
    camera's vertical, too-wide t bounds): the trimmed dense rasterisation
    sums exactly the votes of a vote-by-vote enumeration."""
    from obliq_colmap.registration.raster import HeightBand, VoteRows, rasterise

    rng = np.random.default_rng(5)
    R, half_it, half_o, nh = 400, 6, 4, 5
    B = rng.choice([0.0, 0.25, -0.5, 0.5, 1.0, -1.0], R) + np.where(
        rng.random(R) < 0.3, rng.normal(0, 0.3, R), 0.0
    )
    A = rng.integers(-6, 7, R) + rng.choice([0.0, 0.5, -0.5], R)
    A = np.where(rng.random(R) < 0.2, rng.normal(0, 4, R), A)
    # t bounds up to one beyond where the votes end.
    t_lo = -half_it + rng.integers(-1, 3, R).astype(float)
    t_hi = half_it - rng.integers(-1, 3, R).astype(float)
    # Cells laid out (height, other, t).
    n_o, n_t = 2 * half_o + 1, 2 * half_it + 1
    size = nh * n_o * n_t
    rows = VoteRows(
        A,
        B,
        np.full(R, half_o),
        np.maximum(t_lo, -half_it),
        np.minimum(t_hi, half_it),
        np.full(R, float(half_o * n_t + half_it)),
        np.ones(R),
        np.full(R, float(n_t)),
        rng.uniform(1, 60, R),
    )
    d_h, h_lo = 2.0, -4.0
    hB = rng.choice([0.0, 0.5, -1.0, 2.0], R)
    hA = h_lo + d_h * rng.integers(-2, nh + 2, R) + rng.choice([0.0, 1.0, -1e-13], R)
    TA = rng.choice([-1.0, 0.0, 3.0], R)
    TB = rng.choice([0.0, 0.5, -0.5], R)
    band = HeightBand(hA, hB, TA, TB, h_lo, d_h, nh, float(n_o * n_t))

    def enumerate_votes(b, rows_of_group):
        want = np.zeros(size)
        for r in rows_of_group:
            for t in np.arange(rows.t_lo[r], rows.t_hi[r] + 1):
                k = np.rint(A[r] + B[r] * t)
                if abs(k) > half_o:
                    continue
                cell = rows.base[r] + rows.stride_t[r] * t + rows.stride_o[r] * k
                if b is not None:
                    ih = np.floor((hA[r] + hB[r] * t - h_lo) / d_h)
                    if not (0 <= ih < nh and TA[r] + TB[r] * t > 0):
                        continue
                    cell += b.stride * ih
                want[int(cell)] += rows.weight[r]
        return want

    for b in (None, band):
        want = enumerate_votes(b, range(R))
        assert np.count_nonzero(want) > 50
        np.testing.assert_array_equal(rasterise(rows, b, size), want)
        # Four groups of rows voting into four disjoint ranges of cells.
        want = np.concatenate(
            [enumerate_votes(b, range(g * R // 4, (g + 1) * R // 4)) for g in range(4)]
        )
        got = rasterise(rows, b, size, groups=4)
        np.testing.assert_array_equal(got, want)


def test_pair_distances_fused_equal_projection_then_mahalanobis(block):
    """The RANSAC's fused distances are bit-identical to projecting the
    corners and measuring them (corners behind the camera included)."""
    from obliq_colmap.registration.segments import mahalanobis2, pair_d2

    view, segs, corner_rel, ii, jj = _small_problem(block, 200)
    rng = np.random.default_rng(2)
    H = 64
    alpha = rng.normal(0, 0.02, H)
    c_xy = rng.normal(0, 5, (H, 2))
    xy = corner_rel[ii]
    xy[:5] = -xy[:5] * 3  # behind the camera
    z = view.c0[2] - 250 + rng.normal(0, 20, (H, len(ii)))
    px, _ = view.project(alpha, c_xy, xy, z)
    want = mahalanobis2(px, segs, jj, 5.0)
    got = pair_d2(view, segs, jj, alpha, c_xy, xy, z, 5.0)
    assert np.isinf(want).any() and np.isfinite(want).any()
    np.testing.assert_array_equal(got, want)


def test_t_interval_brute_force():
    """The integer solutions of lo <= A + B t <= hi, also for B = 0 and for
    non-finite rows (none)."""
    from obliq_colmap.registration.raster import t_interval

    rng = np.random.default_rng(1)
    A = rng.normal(0, 8, 300)
    B = rng.normal(0, 1, 300)
    B[::7] = 0.0
    A[::11], A[5], B[6] = np.inf, np.nan, np.nan
    lo = rng.normal(-3, 1, 300)
    for hi in (lo + rng.uniform(0, 6, 300), np.inf):
        t_lo, t_hi = t_interval(A, B, lo, hi)
        t = np.arange(-200, 201)[:, None]
        with np.errstate(invalid="ignore"):
            x = A + B * t
            want = (lo <= x) & (x <= hi) & np.isfinite(A) & ~np.isnan(B)
        np.testing.assert_array_equal((t_lo <= t) & (t <= t_hi), want)
        assert want.any() and not want.all()


@pytest.mark.slow
def test_head_focal_from_the_consensus_of_its_images(tmp_path):
    """Three images of one lens registered with the priors' focal 3 % off and
    held (on ``paper`` each image's refinement keeps 45-86 % of its head's
    error: a weakly observed focal, and inliers chosen with the wrong one):
    the sum of their consensus profiles, each image re-scored with a focal
    held, peaks at the true focal, and an image refined with it is closer
    to its true pose."""
    rng = np.random.default_rng(5)
    options = RegistrationOptions(prior_focal_sigma=0.03, chance_trials=0)
    held = dataclasses.replace(options, refine_focal=False)
    images = []
    for heading in (10.0, 35.0, 60.0):
        blk = make_block(0, num_outliers=60, tmp_path=tmp_path, heading_deg=heading)
        camera = blk.camera.with_focal_scaled(1.03)  # the priors' focal
        seg = blk.segments + rng.normal(0.0, 0.3, blk.segments.shape)
        prior = perturbed_prior(blk.pose, 2)
        result = register_image(
            seg,
            vertical_of(blk.pose),
            camera,
            prior,
            blk.cadastre,
            held,
            segments_undistorted=True,
        )
        assert result.success, result.message
        images.append((blk, camera, seg, result))

    def profile(log_scales):
        return sum(
            focal_profile(r, cam, np.exp(log_scales), seg, cam, b.cadastre, options)
            for b, cam, seg, r in images
        )

    log_scale = consensus_peak(profile, options.prior_focal_sigma)
    # measured: 1.03 * exp(peak) = 1.0004; every image alone: 1.03
    assert abs(1.03 * math.exp(log_scale) - 1.0) < 0.003
    blk, camera, seg, result = images[0]
    head = camera.with_focal_scaled(math.exp(log_scale))
    again = refine_with_camera(result, head, seg, camera, blk.cadastre, options)
    assert again.success and again.camera is head
    errors = [
        (
            rotation_angle_deg(r.cam_from_world.rotation, blk.pose.rotation),
            np.linalg.norm(r.cam_from_world.center[:2] - blk.pose.center[:2]),
        )
        for r in (result, again)
    ]
    # measured: 2.33 -> 0.066 deg, 2.09 -> 0.21 m
    assert errors[1][0] < errors[0][0] / 3 and errors[1][1] < errors[0][1] / 3
