"""Tie points: tracks, triangulation, and the Schur elimination of 3-D points."""

from __future__ import annotations

import cv2
import numpy as np
import pycolmap
import pytest

from obliq_colmap.adjustment.ties import triangulate_tie_tracks


def _block(rng, n_images: int):
    """Cameras 500 m up looking down-ish at a 200 m square."""
    cams, poses = [], []
    for i in range(n_images):
        cams.append(
            pycolmap.Camera(
                model="PINHOLE", width=1000, height=700, params=[1200, 1200, 500, 350]
            )
        )
        c = np.array([40.0 * i, 10.0 * (i % 2), 500.0])
        R = np.diag([1.0, -1.0, -1.0])  # looking straight down
        poses.append(pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ c))
    return cams, poses


def test_triangulate_tie_tracks_recovers_points_within_noise():
    rng = np.random.default_rng(0)
    cams, poses = _block(rng, 4)
    X = np.c_[rng.uniform(-50, 150, (50, 2)), rng.uniform(0, 30, 50)]
    track = np.repeat(np.arange(50), 4)
    image = np.tile(np.arange(4), 50)
    sigma = 0.3
    xy = np.concatenate(
        [
            cams[i].img_from_cam(poses[i] * X[t][None])
            for t, i in zip(track, image, strict=True)
        ]
    )
    xy += rng.normal(0, sigma, xy.shape)
    est = triangulate_tie_tracks(cams, poses, track, image, xy)
    # depth sd ~ sigma / f * Z^2 / baseline (~120 m), ground sd ~ sigma / f * Z
    err = np.abs(est - X)
    assert np.median(err[:, :2]) < 3 * sigma / 1200 * 500
    assert np.median(err[:, 2]) < 3 * sigma / 1200 * 500**2 / 120
    assert np.max(err[:, 2]) > 0  # noise reached the points


@pytest.mark.slow
def test_tie_points_on_sample_fit_true_poses():
    """On the 16-image sample with the true poses, verified tracks reproject
    to within SIFT's noise (sub-pixel median)."""
    from pathlib import Path

    import cv2

    from obliq_colmap.adjustment.ties import TiePointOptions, tie_points

    root = Path(__file__).resolve().parents[1] / "data_samples" / "oblique_small"
    rec = pycolmap.Reconstruction(root / "gt")
    images = sorted(rec.images.values(), key=lambda im: im.name)[:6]
    gray = [
        cv2.imread(str(root / "images" / im.name), cv2.IMREAD_GRAYSCALE)
        for im in images
    ]
    cams = [rec.cameras[im.camera_id] for im in images]
    poses = [im.cam_from_world() for im in images]
    ties = tie_points(gray, cams, poses, 100.0, TiePointOptions(max_num_features=1000))
    assert len(ties.xyz) > 10
    err = [
        np.linalg.norm(
            cams[i].img_from_cam(poses[i] * ties.xyz[ties.obs_point[m]])
            - ties.obs_xy[m],
            axis=1,
        )
        for i in range(len(images))
        if (m := ties.obs_image == i).any()
    ]
    assert np.median(np.concatenate(err)) < 1.0


def test_tracks_chain_matches_and_drop_inconsistent_ones():
    from obliq_colmap.adjustment.ties import chain_tie_tracks

    # image 0 feature 0 -> image 1 feature 2 -> image 2 feature 1: one track;
    # image 0 features 3 and 4 both reach image 1 feature 5: seen twice, dropped
    matches = {
        (0, 1): np.array([[0, 2], [3, 5], [4, 5]]),
        (1, 2): np.array([[2, 1]]),
    }
    track, image, feature = chain_tie_tracks(matches, [6, 6, 6])
    assert len(np.unique(track)) == 1
    np.testing.assert_array_equal(np.sort(image), [0, 1, 2])
    np.testing.assert_array_equal(feature[np.argsort(image)], [0, 2, 1])


def test_select_pairs_needs_overlap_and_similar_views():
    from obliq_colmap.adjustment.ties import TiePointOptions, footprints, select_pairs

    cams, poses = _block(np.random.default_rng(2), 4)
    # a fifth camera far away (no overlap) and a sixth over image 0 but
    # tilted 60 deg (overlaps, yet SIFT would not match across that angle)
    c = np.array([5000.0, 0.0, 500.0])
    R = np.diag([1.0, -1.0, -1.0])
    far = pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ c)
    a = np.radians(60)
    tilt = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    R2 = tilt @ R
    c2 = np.array([0.0, 500 * np.tan(a), 500.0])
    tilted = pycolmap.Rigid3d(pycolmap.Rotation3d(R2), -R2 @ c2)
    cams, poses = cams + cams[:2], poses + [far, tilted]
    polys = footprints(cams, poses, 0.0)
    assert polys[5].intersects(polys[0])
    pairs = select_pairs(polys, poses, TiePointOptions(max_view_angle_deg=40.0))
    assert all(4 not in p and 5 not in p for p in pairs)
    assert (0, 1) in pairs and (2, 3) in pairs
    # by default two heads 90 deg apart are matched (the far one never)
    pairs = select_pairs(polys, poses, TiePointOptions())
    assert (0, 5) in pairs and all(4 not in p for p in pairs)


@pytest.mark.slow
def test_register_observes_tie_points_in_the_bundle_and_writes_them(tmp_path):
    """``register`` (tie points on by default): the bundle's tie points reach
    points3D.bin with tracks across images, reprojecting within SIFT's noise
    at the written poses, and every image of the sample stays within 2 px."""
    from pathlib import Path

    from obliq_colmap.evaluate import EvaluateOptions, evaluate_model
    from obliq_colmap.pipeline import PipelineOptions, run_register, write_run

    sample = Path(__file__).resolve().parents[1] / "data_samples" / "oblique_small"
    options = PipelineOptions(num_workers=1, progress=False)
    run = run_register(
        sample / "images", sample / "cadastre.geojson", sample / "priors", options
    )
    ties = run.report["tie_points"]
    assert ties["num_points"] > 100 and ties["median_per_image"] > 20
    write_run(tmp_path / "model", run)
    rec = pycolmap.Reconstruction(tmp_path / "model")
    rec.update_point_3d_errors()
    assert rec.num_points3D() == len(run.points3D)
    assert rec.compute_mean_reprojection_error() < 1.0
    ev = evaluate_model(tmp_path / "model", sample, EvaluateOptions())
    dev = np.array([r.mean_deviation_px for r in ev.images])
    assert len(dev) == 16 and np.all(dev < 2.0), dev


def _block_without_one_image():
    """A synthetic block with tie points (1500, 0.3 px) solved at the truth
    but for its 6th image: (syn, image ids, that image's id, cameras by
    image id, the block's state without it)."""
    from obliq_colmap.state import BlockState
    from obliq_colmap.synthetic.bundle_problem import make_synthetic_problem

    syn = make_synthetic_problem(seed=2, tie_points=1500, noise_px=0.3)
    P = syn.problem
    ids = list(P.image_ids)
    out = ids[5]
    cams = {i: syn.cameras[P.image_camera[i]] for i in ids}
    state = BlockState(
        poses={i: syn.poses[i] for i in ids if i != out},
        cameras={i: cams[i] for i in ids if i != out},
        planes={i: np.zeros(3) for i in ids if i != out},
    )
    return syn, ids, out, cams, state


def test_a_failed_image_is_placed_by_its_tie_points():
    """An image left out of the solved block is placed by its tie
    observations of the tracks the block triangulates: at the truth's pose
    within the noise (0.3 px), and not at all with too few observations."""
    from obliq_colmap.adjustment.ties import TiePoints
    from obliq_colmap.pipeline.resection import MIN_INLIERS, tie_resections

    syn, ids, out, cams, state = _block_without_one_image()
    P = syn.problem
    ties = TiePoints(
        syn.tie_xyz,
        P.tie_point,
        P.tie_image,
        P.tie_xy,
        np.zeros(len(P.tie_xy), np.int64),
        image_ids=tuple(ids),
    )
    assert (P.tie_image == 5).sum() > MIN_INLIERS
    placed = tie_resections(state, ties, {out: cams[out]})
    truth = syn.poses[out]
    assert np.linalg.norm(placed[out].center - truth.center) < 0.3
    R = placed[out].rotation @ truth.rotation.T
    assert np.degrees(np.arccos(np.clip((np.trace(R) - 1) / 2, -1, 1))) < 0.02
    few = TiePoints(
        syn.tie_xyz,
        P.tie_point[: MIN_INLIERS * 3],
        P.tie_image[: MIN_INLIERS * 3],
        P.tie_xy[: MIN_INLIERS * 3],
        np.zeros(MIN_INLIERS * 3, np.int64),
        image_ids=tuple(ids),
    )
    assert tie_resections(state, few, {out: cams[out]}) == {}


def test_an_image_pair_on_a_wrong_geometry_is_left_out():
    """Tracks of a pair whose matches all sit pixels off at the solved block
    (a two-view geometry verified on repeated texture) are dropped with every
    track that sees that pair; a lone bad match is not a pair."""
    from obliq_colmap.adjustment.ties import consistent_pairs

    rng = np.random.default_rng(0)
    image, point, err = [], [], []
    t = 0
    for i, j, e in [(0, 1, 0.4), (1, 2, 0.5), (2, 3, 6.0), (0, 2, 0.3)]:
        for _ in range(20):
            image += [i, j]
            point += [t, t]
            err += list(np.abs(rng.normal(e, 0.1 * e, 2)))
            t += 1
    # a three-view track through the bad pair, and one wild match elsewhere
    image += [1, 2, 3]
    point += [t, t, t]
    err += [0.4, 0.5, 6.0]
    err[0] = 9.0
    good = consistent_pairs(
        np.array(err), np.array(image), np.array(point), factor=3.0, floor_px=3.0
    )
    assert good.shape == (t + 1,)
    assert not good[40:60].any() and not good[t]
    assert good[:40].all() and good[60:t].all()


def test_a_tie_point_must_lie_in_the_scene():
    """Between the ground (less 0.2 flying heights) and the cameras, and within
    5 flying heights of one: a wrong match along an epipolar line lands
    anywhere on it and reprojects well, so its position is what gives it away."""

    from obliq_colmap.adjustment.ties import TiePointOptions, in_the_scene

    poses = [
        pycolmap.Rigid3d(pycolmap.Rotation3d(), -np.array([x, 0.0, 500.0]))
        for x in (0.0, 200.0)
    ]
    xyz = np.array(
        [
            [100.0, 50.0, 10.0],  # on a roof: kept
            [100.0, 50.0, -50.0],  # 50 m below the ground: kept (slope, datum)
            [100.0, 50.0, -200.0],  # 200 m below: a wrong match
            [100.0, 50.0, 600.0],  # above the cameras
            [5000.0, 0.0, 0.0],  # 10 flying heights away
        ]
    )
    ok = in_the_scene(xyz, poses, 0.0, TiePointOptions())
    assert ok.tolist() == [True, True, False, False, False]


def test_mutual_ratio_matches_finds_the_planted_pairs_and_drops_ambiguous_ones():
    """Descriptors of image b are those of a, shuffled and slightly changed,
    plus clutter: the planted pairs come back; a descriptor with a near twin
    in b fails the ratio test; one far from everything fails max_angle."""
    from obliq_colmap.adjustment.tie_matching import mutual_ratio_matches

    rng = np.random.default_rng(3)
    a = rng.random((200, 128)) ** 4
    perm = rng.permutation(200)
    b = a[perm] + rng.normal(0, 0.002, (200, 128))
    b = np.vstack([b, rng.random((100, 128)) ** 4])
    b[200] = b[np.flatnonzero(perm == 7)[0]] + 1e-4  # a twin of a's 7th
    m = mutual_ratio_matches(a, b, max_ratio=0.8)
    found = dict(m.tolist())
    assert 7 not in found
    truth = {int(perm[j]): j for j in range(200)}
    assert len(found) >= 190
    assert all(truth[i] == j for i, j in found.items())
    assert len(mutual_ratio_matches(a, -b, 0.8, max_angle=0.7)) == 0


def test_ratio_best_is_the_ratio_test_on_the_two_largest_per_row_and_column():
    """Against a full sort: the best partner per row and per column, and the
    ratio test on the two largest; a tied best fails it (no unique nearest)."""
    from obliq_colmap.adjustment.tie_matching import _ratio_best

    rng = np.random.default_rng(5)
    S = rng.uniform(0.2, 1.0, (60, 70)).astype(np.float32)
    S[3, [10, 40]] = 0.99  # a tie for the best of row 3
    kept = S.copy()
    for axis in (1, 0):
        got = _ratio_best(S, axis, 0.9, 0.7)
        M = S if axis == 1 else S.T
        order = np.argsort(-M, axis=1, kind="stable")
        v = np.take_along_axis(M, order[:, :2], axis=1)
        a1, a2 = np.arccos(v[:, 0]), np.arccos(v[:, 1])
        want = np.where((a1 < 0.9 * a2) & (a1 <= 0.7), order[:, 0], -1)
        np.testing.assert_array_equal(got, want)
    assert _ratio_best(S, 1, 0.9, 0.7)[3] == -1
    np.testing.assert_array_equal(S, kept)  # the masking is undone


def test_first_argmax_down_is_numpys_argmax_down_the_columns_ties_included():
    from obliq_colmap.adjustment.tie_matching import _first_argmax_down

    rng = np.random.default_rng(8)
    S = rng.integers(0, 4, (50, 70)).astype(np.float32)  # many tied maxima
    S[:, 5] = 2.0  # a column that is one tie
    np.testing.assert_array_equal(_first_argmax_down(S), np.argmax(S, axis=0))


def test_keypoints_scaled_back_per_axis():
    # 2004 x 1336 down-sampled to 1000 x 667: x and y scale differ (0.499 and
    # 0.49925); one scale for both put the bottom rows 0.7 px off.
    from obliq_colmap.adjustment.tie_matching import _scaled, _sift_arrays

    rng = np.random.default_rng(3)
    img = cv2.resize(
        rng.integers(0, 255, (167, 251)).astype(np.uint8),
        (2004, 1336),
        interpolation=cv2.INTER_CUBIC,
    )
    k, _, _, scale = _sift_arrays((img, 1000, 200, 0, 1))
    np.testing.assert_allclose(scale, [1000 / 2004, 667 / 1336])
    assert len(k) > 50 and k[:, 1].max() < 667
    cam = _scaled(
        pycolmap.Camera(
            model="SIMPLE_RADIAL", width=2004, height=1336, params=[3000, 1002, 668, 0]
        ),
        scale,
    )
    assert (cam.width, cam.height) == (1000, 667)


def test_a_nadir_image_gets_nadir_partners_among_larger_oblique_footprints():
    """A nadir footprint lies inside the oblique ones (overlap share 1), which
    would take all its places although SIFT matches across 45 deg poorly:
    half of its partners are its best ones of a similar view."""
    from shapely.geometry import box

    from obliq_colmap.adjustment.ties import TiePointOptions, select_pairs
    from obliq_colmap.synthetic.cameras import rotation_from_angles

    def rig(heading: float, tilt: float) -> pycolmap.Rigid3d:
        R = rotation_from_angles(heading, tilt, 0.0)
        return pycolmap.Rigid3d(pycolmap.Rotation3d(R), np.zeros(3))

    # three nadir images in a row (40 % overlap), ten obliques over all
    nadir = [box(60.0 * k, 0.0, 60.0 * k + 100.0, 60.0) for k in range(3)]
    oblique = [box(-100.0 - k, -100.0, 300.0 + k, 200.0) for k in range(10)]
    polys = nadir + oblique
    poses = [rig(0.0, 0.0)] * 3 + [rig(90.0 * (k % 4), 45.0) for k in range(10)]
    pairs = select_pairs(polys, poses, TiePointOptions(max_pairs_per_image=8))
    assert (0, 1) in pairs and (1, 2) in pairs
    assert sum(1 for p in pairs if p[0] == 1 and p[1] >= 3) >= 4  # obliques too


def test_images_of_a_new_head_place_each_other_in_rounds():
    """An image whose tracks the block sees once only (the rest of its views
    are in another unplaced image of the same new head) is placed once that
    image is: only when the two are chained."""
    from obliq_colmap.adjustment.ties import TiePoints
    from obliq_colmap.pipeline.resection import MIN_INLIERS, tie_resections
    from obliq_colmap.state import BlockState
    from obliq_colmap.synthetic.bundle_problem import make_synthetic_problem

    syn = make_synthetic_problem(seed=2, tie_points=3000, noise_px=0.3)
    P = syn.problem
    ids = list(P.image_ids)
    a, b = 4, 5  # indices into ids, neighbours
    img, pt = P.tie_image, P.tie_point
    both = np.intersect1d(pt[img == a], pt[img == b])
    keep = np.ones(len(img), bool)
    for t in both:  # one block view only, besides a and b
        block_obs = np.flatnonzero((pt == t) & (img != a) & (img != b))
        keep[block_obs[1:]] = False
    keep &= ~((img == b) & ~np.isin(pt, both))  # b sees nothing else
    has_block = np.array(
        [np.any((pt == t) & keep & (img != a) & (img != b)) for t in both]
    )
    assert has_block.sum() > MIN_INLIERS * 1.5
    ties = TiePoints(
        syn.tie_xyz,
        pt[keep],
        img[keep],
        P.tie_xy[keep],
        np.zeros(int(keep.sum()), np.int64),
        image_ids=tuple(ids),
    )
    cams = {i: syn.cameras[P.image_camera[i]] for i in ids}
    out = {ids[a], ids[b]}
    state = BlockState(
        poses={i: syn.poses[i] for i in ids if i not in out},
        cameras={i: cams[i] for i in ids if i not in out},
        planes={i: np.zeros(3) for i in ids if i not in out},
    )
    todo = {i: cams[i] for i in out}
    assert set(tie_resections(state, ties, todo)) == {ids[a]}
    placed = tie_resections(state, ties, todo, frozenset(out))
    assert set(placed) == out
    truth = syn.poses[ids[b]]
    assert np.linalg.norm(placed[ids[b]].center - truth.center) < 0.5


def test_a_tie_resection_does_not_depend_on_what_ran_before():
    """pycolmap's RANSAC without a seed draws from its thread's generator,
    whose state is whatever ran before in the process: the same image must
    come out at the same pose after any other estimation."""
    import pycolmap

    from obliq_colmap.adjustment.ties import TiePoints
    from obliq_colmap.pipeline.resection import tie_resections

    syn, ids, out, cams, state = _block_without_one_image()
    P = syn.problem
    # 40 % of the image's observations wrong, many near the inlier threshold,
    # so that which ones a draw keeps decides the refined pose's last digits
    rng = np.random.default_rng(1)
    xy = P.tie_xy.copy()
    mine = np.flatnonzero(P.tie_image == 5)
    bad = rng.choice(mine, int(0.4 * len(mine)), replace=False)
    xy[bad] += rng.uniform(-15.0, 15.0, (len(bad), 2))
    ties = TiePoints(
        syn.tie_xyz,
        P.tie_point,
        P.tie_image,
        xy,
        np.zeros(len(xy), np.int64),
        image_ids=tuple(ids),
    )

    def unseeded_estimations():
        X = rng.uniform(-50, 50, (200, 3)) + [0, 0, 500]
        x = rng.uniform(0, 1000, (200, 2))
        cam = pycolmap.Camera(model="SIMPLE_PINHOLE", width=1000, height=1000,
                              params=[1000, 500, 500])  # fmt: skip
        for _ in range(3):
            pycolmap.estimate_and_refine_absolute_pose(x, X, cam)

    first = tie_resections(state, ties, {out: cams[out]})[out]
    unseeded_estimations()
    again = tie_resections(state, ties, {out: cams[out]})[out]
    np.testing.assert_array_equal(first.rotation, again.rotation)
    np.testing.assert_array_equal(first.center, again.center)


def test_an_image_placed_by_ties_that_the_bundle_no_longer_holds_is_left_out():
    """A tie-placed image (no map corner of its own) whose tie observations
    in the last bundle are of points that at most one other image sees is
    held along epipolar lines only: left out, saying why; one with enough
    points seen by two others stays, and so does an image with map corners."""
    from types import SimpleNamespace

    from obliq_colmap.geometry import Pose
    from obliq_colmap.pipeline import leave_out_rejected, unsupported_placements
    from obliq_colmap.state import BlockState

    # tracks 0-39 seen by images 0, 1, 2; tracks 40-79 by images 0 and 3 only
    img = np.r_[np.tile([0, 1, 2], 40), np.tile([0, 3], 40)]
    pt = np.r_[np.repeat(np.arange(40), 3), np.repeat(np.arange(40, 80), 2)]
    ids = (10, 11, 12, 13)
    stage3 = SimpleNamespace(
        bundle_problem=SimpleNamespace(tie_point=pt, tie_image=img, image_ids=ids),
        bundle_precision={},
    )

    def outcome(name, by_ties, inliers):
        return SimpleNamespace(
            name=name,
            placed_by_ties=by_ties,
            registration=SimpleNamespace(num_inliers=inliers),
            status="registered",
            message="",
        )

    outcomes = {
        10: outcome("A", False, 50),
        11: outcome("B", True, 0),  # 40 observations of 3-view points
        12: outcome("C", False, 20),
        13: outcome("D", True, 0),  # 40 observations, all of 2-view points
    }
    pose = Pose(np.eye(3), np.zeros(3))
    state = BlockState(
        poses={i: pose for i in ids},
        cameras={},
        planes={i: np.zeros(3) for i in ids},
    )
    out = unsupported_placements(state, stage3, outcomes, 30)
    assert out == [13]
    assert unsupported_placements(state, stage3, outcomes, 41) == [11, 13]
    state = leave_out_rejected(state, stage3, outcomes, [], unsupported=out)
    assert set(state.poses) == {10, 11, 12}
    assert outcomes[13].status == "failed"
    assert "only 0 of its tie observations" in outcomes[13].message


def test_keypoint_scales_are_in_full_resolution_pixels():
    """SIFT on the sample image down-sampled to half and at full size: the
    keypoints found at one place have one scale in full-resolution pixels
    (the scale the tie rows' sd follows), within SIFT's own scale steps."""
    from pathlib import Path

    from scipy.spatial import cKDTree

    from obliq_colmap.adjustment.tie_matching import extract_features
    from obliq_colmap.adjustment.tie_options import TiePointOptions

    image = Path(__file__).parents[1] / "data_samples/oblique_small/images/N_00.jpg"
    found = []
    for size in (1000, 500):
        options = TiePointOptions(max_image_size=size, num_workers=1)
        xy, _, _, _, scale = extract_features([image], options)[0]
        found.append((xy, scale))
    (xy_full, s_full), (xy_half, s_half) = found
    assert np.all(s_full > 0) and np.all(s_half > 0)
    d, j = cKDTree(xy_full).query(xy_half)
    same = d < 1.0
    assert same.sum() > 100
    ratio = s_half[same] / s_full[j[same]]
    assert np.median(ratio) == pytest.approx(1.0, abs=0.1)
