"""Stage 3: facade edges in wall bands, pairwise matching, tracks as 3D lines.

Every test builds its scene from exact geometry (a map of one or a few
buildings, oblique cameras, horizontal and vertical 3D segments projected
with the true cameras), so the expected heights, offsets and matches are
known exactly; tolerances follow from the injected pixel noise.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from obliq_colmap.adjustment import (
    FacadeOptions,
    MatchingOptions,
    datum_corrections,
    facade_edges,
    match_facade_edges,
    match_pair,
    triangulate_tracks,
)
from obliq_colmap.cadastre import load_cadastre
from obliq_colmap.geometry import Camera, Pose

F, W, H = 2400.0, 2000, 1334


def _camera() -> Camera:
    return Camera("PINHOLE", W, H, [F, F, W / 2 + 3.0, H / 2 - 5.0], 1)


def _oblique_pose(center: np.ndarray, heading_deg: float, tilt_deg: float = 45.0):
    """Camera looking along ``heading`` (deg from +y towards +x), tilted from
    nadir by ``tilt`` (COLMAP: x right, y down, z forward)."""
    h, t = np.radians(heading_deg), np.radians(tilt_deg)
    forward = np.array([np.sin(h) * np.sin(t), np.cos(h) * np.sin(t), -np.cos(t)])
    right = np.array([np.cos(h), -np.sin(h), 0.0])
    down = np.cross(forward, right)
    R = np.stack([right, down, forward])  # rows: camera axes in world
    return Pose.from_center(R, center)


def _map(tmp_path, rings: list[list[tuple[float, float]]]):
    feats = [
        {
            "type": "Feature",
            "properties": {"id": f"b{k}"},
            "geometry": {"type": "Polygon", "coordinates": [list(map(list, r))]},
        }
        for k, r in enumerate(rings)
    ]
    path = tmp_path / "map.geojson"
    path.write_text(
        json.dumps(
            {
                "type": "FeatureCollection",
                "crs": {"type": "name", "properties": {"name": "EPSG:25832"}},
                "features": feats,
            }
        )
    )
    return load_cadastre(path, origin=np.zeros(3))


def _box(x0, y0, w, d):
    return [(x0, y0), (x0 + w, y0), (x0 + w, y0 + d), (x0, y0 + d), (x0, y0)]


def _project(camera: Camera, pose: Pose, X: np.ndarray) -> np.ndarray:
    return camera.img_from_cam(pose.transform(X.reshape(-1, 3))).reshape(
        X.shape[:-1] + (2,)
    )


def _south_wall_segments(y_wall, x0, x1, heights, ground=0.0, offset=0.0):
    """(K, 2, 3) horizontal 3D segments along the south wall y = y_wall,
    ``offset`` metres in front of it (south), from x0 to x1."""
    return np.array(
        [
            [[x0, y_wall - offset, ground + h], [x1, y_wall - offset, ground + h]]
            for h in heights
        ]
    )


@pytest.fixture()
def scene(tmp_path):
    # One 40 x 20 m building, south wall at y = 100, seen by cameras south of
    # it looking north (heading 0) from ~600 m slant distance.
    cad = _map(tmp_path, [_box(-20.0, 100.0, 40.0, 20.0)])
    cams = [
        _oblique_pose(np.array([x, 100.0 - 420.0, 420.0]), 0.0) for x in (-60.0, 60.0)
    ]
    return cad, _camera(), cams


def test_horizontal_wall_segments_are_found_at_their_heights(scene):
    cad, cam, (pose, _) = scene
    heights = np.array([0.0, 3.1, 6.2, 9.3, 14.0])
    segs3 = _south_wall_segments(100.0, -15.0, 12.0, heights)
    px = _project(cam, pose, segs3)
    # distractors: a vertical edge on the wall, a horizontal edge across the
    # wall's direction (a street marking going north), a short segment
    vert = _project(cam, pose, np.array([[[5.0, 100.0, 0.0], [5.0, 100.0, 12.0]]]))
    cross = _project(cam, pose, np.array([[[0.0, 95.0, 0.0], [0.0, 70.0, 0.0]]]))
    short = _project(cam, pose, np.array([[[0.0, 100.0, 4.0], [0.3, 100.0, 4.0]]]))
    ends = np.concatenate([px, vert, cross, short])
    d = ends[:, 1] - ends[:, 0]
    normals = np.column_stack([d[:, 1], -d[:, 0]]) / np.linalg.norm(d, axis=1)[:, None]
    fe = facade_edges(ends, normals, cam, pose, lambda xy: np.zeros(len(xy)), cad)
    south = np.flatnonzero(np.abs(cad.edge_normal[:, 1] + 1) < 1e-9)
    on_south = fe.edge == south[0]
    assert set(fe.segment[on_south]) == set(range(len(heights)))
    order = np.argsort(fe.segment[on_south])
    np.testing.assert_allclose(fe.height[on_south][order], heights, atol=1e-6)
    # every kept row is one of the wall's horizontals (no distractor)
    assert set(fe.segment) <= set(range(len(heights)))
    # px_per_m: the image length of one metre of the wall's vertical
    up = _project(cam, pose, np.array([[0.0, 100.0, 1.0], [0.0, 100.0, 0.0]]))
    assert fe.px_per_m[on_south].min() == pytest.approx(
        np.linalg.norm(up[0] - up[1]), rel=0.2
    )


def test_pixel_tolerances_are_in_detection_pixels(scene):
    """Segments detected at half resolution (``pixel_scale`` 2): the length
    and direction tolerances are in those pixels, i.e. twice as many pixels
    of the full image."""
    cad, cam, (pose, _) = scene
    px = _project(cam, pose, _south_wall_segments(100.0, -10.0, 10.0, [3.0, 8.0]))
    d = px[:, 1] - px[:, 0]
    n = np.column_stack([d[:, 1], -d[:, 0]]) / np.linalg.norm(d, axis=1)[:, None]
    o = FacadeOptions()
    # segment 0: one end moved 4 px across, both ends 2 px off the wall's
    # horizontal through the midpoint (1.5 px allowed at full resolution, 3 px
    # at half); segment 1: shortened to 20 px (15 / 30 px needed).
    tilted = px.copy()
    tilted[0, 1] += 4.0 * n[0]
    mid = px[1].mean(axis=0)
    u = d[1] / np.linalg.norm(d[1])
    tilted[1] = [mid - 10.0 * u, mid + 10.0 * u]
    z = lambda xy: np.zeros(len(xy))  # noqa: E731
    full = facade_edges(tilted, n, cam, pose, z, cad, o, pixel_scale=1.0)
    half = facade_edges(tilted, n, cam, pose, z, cad, o, pixel_scale=2.0)
    assert set(full.segment) == {1} and set(half.segment) == {0}
    assert np.all(half.pixel_scale == 2.0) and np.all(full.pixel_scale == 1.0)


def test_polarity_says_which_side_is_brighter(scene):
    cad, cam, (pose, _) = scene
    px = _project(cam, pose, _south_wall_segments(100.0, -10.0, 10.0, [5.0]))
    d = px[:, 1] - px[:, 0]
    left = np.column_stack([d[:, 1], -d[:, 0]]) / np.linalg.norm(d, axis=1)[:, None]
    up_img = _project(cam, pose, np.array([[0.0, 100.0, 6.0]]))[0] - px[0].mean(0)
    brighter_up = left if np.dot(left[0], up_img) > 0 else -left
    z = lambda xy: np.zeros(len(xy))  # noqa: E731
    a = facade_edges(px, brighter_up, cam, pose, z, cad)
    b = facade_edges(px, -brighter_up, cam, pose, z, cad)
    assert set(a.polarity) == {1} and set(b.polarity) == {-1}


def _edges_of(cam, pose, cad, segs3, noise_px, rng):
    px = _project(cam, pose, segs3) + rng.normal(0, noise_px, (len(segs3), 2, 2))
    d = px[:, 1] - px[:, 0]
    n = np.column_stack([d[:, 1], -d[:, 0]]) / np.linalg.norm(d, axis=1)[:, None]
    up = _project(cam, pose, segs3[:, :1] + [0, 0, 1.0])[:, 0] - px[:, 0]
    n *= np.sign(np.sum(n * up, axis=1))[:, None]  # all brighter above
    return facade_edges(px, n, cam, pose, lambda xy: np.zeros(len(xy)), cad)


def test_pair_matching_recovers_offset_and_rejects_floor_ambiguity(tmp_path):
    """Window rows every 3 m (same polarity) on four walls; image B sees the
    scene 0.8 m higher plus a tilt and a 1 % height scale: the RANSAC must
    find that offset model, not one shifted by a floor."""
    rng = np.random.default_rng(3)
    cad = _map(
        tmp_path,
        [_box(-60.0 + 35 * k, 100.0 + 7 * (k % 2), 25.0, 15.0) for k in range(4)],
    )
    cam = _camera()
    pa = _oblique_pose(np.array([-30.0, -320.0, 420.0]), 0.0)
    pb = _oblique_pose(np.array([30.0, -320.0, 420.0]), 0.0)
    rows = np.arange(0.0, 22.0, 3.0) + 0.4
    segs = np.concatenate(
        [
            _south_wall_segments(100.0 + 7 * (k % 2), x + 2, x + 20, rows)
            for k, x in enumerate(-60.0 + 35 * np.arange(4))
        ]
    )
    fa = _edges_of(cam, pa, cad, segs, 0.1, rng)
    fb = _edges_of(cam, pb, cad, segs, 0.1, rng)
    # B's own height frame: 0.8 m offset, 0.3 % slope along x, 1 % scale
    anchors_b = cad.edge_xy[fb.edge, 0] + fb.s[:, None] * (
        (cad.edge_xy[fb.edge, 1] - cad.edge_xy[fb.edge, 0])
        / cad.edge_length[fb.edge, None]
    )
    fb.height = (fb.height - 0.8 - 0.003 * anchors_b[:, 0]) / 1.01
    anchors_a = cad.edge_xy[fa.edge, 0] + fa.s[:, None] * (
        (cad.edge_xy[fa.edge, 1] - cad.edge_xy[fa.edge, 0])
        / cad.edge_length[fa.edge, None]
    )
    ra, rb, model, n_cand, _ = match_pair(
        fa, fb, anchors_a, anchors_b, MatchingOptions(), np.random.default_rng(0)
    )
    assert n_cand > len(segs)  # the floor ambiguity is in the candidates
    correct = fa.segment[ra] == fb.segment[rb]
    assert correct.mean() >= 0.95 and len(ra) >= 0.8 * len(segs)


def test_datum_corrections_recover_image_offsets():
    from obliq_colmap.adjustment import PairMatch

    e_true = np.array([2.0, -1.0, 0.5, -1.5])  # zero mean
    pairs = [
        PairMatch(
            a,
            b,
            np.arange(10),
            np.arange(10),
            np.zeros(4),
            e_true[a] - e_true[b],
            10,
            1,
        )
        for a, b in [(0, 1), (1, 2), (2, 3), (0, 3)]
    ]
    np.testing.assert_allclose(datum_corrections(pairs, 5)[:4], e_true, atol=1e-9)
    assert np.isnan(datum_corrections(pairs, 5)[4])  # no match: unknown


def test_tracks_chain_three_images_and_heights_are_absolute(tmp_path):
    rng = np.random.default_rng(5)
    cad = _map(tmp_path, [_box(-20.0 + 30 * k, 100.0, 22.0, 15.0) for k in range(3)])
    cam = _camera()
    poses = [_oblique_pose(np.array([x, -320.0, 420.0]), 0.0) for x in (-50, 0, 50)]
    rows = np.array([0.0, 4.5, 9.7, 16.2])
    segs = np.concatenate(
        [_south_wall_segments(100.0, x + 2, x + 19, rows) for x in (-20, 10, 40)]
    )
    facades = [_edges_of(cam, p, cad, segs, 0.05, rng) for p in poses]
    grounds = np.array([[0, 0, 0.0], [0, 0, 0.0], [0, 0, 0.0]])
    tracks = match_facade_edges(facades, grounds, cad, MatchingOptions())
    assert tracks.num_tracks >= 0.8 * len(segs)
    # a track's observations are one 3D segment (same index in every image)
    seg_of = np.array(
        [facades[i].segment[r] for i, r in zip(tracks.image, tracks.row, strict=True)]
    )
    for j in range(tracks.num_tracks):
        assert len(set(seg_of[tracks.track == j])) == 1
    # heights: the segments' true heights (noise 0.05 px ~ 1 cm)
    true_h = rows[seg_of % len(rows)]
    first = np.unique(tracks.track, return_index=True)[1]
    np.testing.assert_allclose(tracks.height, true_h[first], atol=0.05)


@pytest.mark.parametrize("offset", [0.0, 0.45, -1.2])
def test_triangulated_track_finds_a_line_off_the_wall(offset):
    """A roof rim 0.45 m in front of the wall (overhang), seen from two
    directions: the track's line is recovered at its offset and height."""
    cam = _camera()
    poses = [
        _oblique_pose(np.array([-300.0, -300.0, 420.0]), 45.0),
        _oblique_pose(np.array([300.0, -300.0, 420.0]), -45.0),
        _oblique_pose(np.array([0.0, -400.0, 420.0]), 0.0),
    ]
    seg = _south_wall_segments(100.0, -5.0, 5.0, [12.0], offset=offset)[0]
    ends = np.stack([_project(cam, p, seg) for p in poses])  # (3, 2, 2)

    def solve(sigma):
        return triangulate_tracks(
            np.arange(3),
            np.zeros(3, np.int64),
            ends,
            [cam] * 3,
            poses,
            np.array([[0.0, 100.0]]),
            np.array([[0.0, -1.0]]),  # outward normal of the south wall
            np.full(3, 5.0),
            offset_sigma_m=sigma,
        )

    d, h = solve(1e6)  # (practically) no prior: exact
    assert d[0] == pytest.approx(offset, abs=1e-6)
    assert h[0] == pytest.approx(12.0, abs=1e-6)
    d, _ = solve(1e-3)  # a tight prior holds the line on the wall
    assert abs(d[0]) < 1e-3


def test_facade_options_are_checked():
    with pytest.raises(ValueError):
        FacadeOptions(height_range_m=(5.0, -5.0))
    with pytest.raises(ValueError):
        MatchingOptions(confidence=1.0)


def test_a_nadir_view_is_told_from_an_oblique_one():
    """``near_nadir``: the vertical VP inside the image (a nadir camera, or
    one tilted less than half its vertical field of view) against outside
    (the 45 deg obliques); such an image gives the bundle neither a VP row
    nor facade rows."""
    import numpy as np

    from obliq_colmap.adjustment.problem import near_nadir
    from obliq_colmap.geometry import Camera, Pose
    from obliq_colmap.synthetic.cameras import rotation_from_angles

    cam = Camera("PINHOLE", 2004, 1336, [2420.0, 2420.0, 1002.0, 668.0])
    half_fov_v = np.degrees(np.arctan(668.0 / 2420.0))  # 15.4 deg
    for heading in (0.0, 90.0, 215.0):
        for tilt, expected in ((0.0, True), (half_fov_v - 1, True), (45.0, False)):
            R = rotation_from_angles(heading, tilt, 0.5)
            pose = Pose.from_center(R, np.array([10.0, -5.0, 600.0]))
            assert near_nadir(cam, pose) is expected, (heading, tilt)
