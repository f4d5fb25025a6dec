"""The map corners' ground heights written into points3D (issue 28: the
terrain and building heights are made from them)."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from obliq_colmap.colmap_io import Block, ImageRecord
from obliq_colmap.geometry import Camera, Pose
from obliq_colmap.pipeline.output import _corner_ground, _rebased_planes


def _ground(xy: np.ndarray) -> np.ndarray:
    """(N,) true terrain at (N, 2): a 3 % slope to the north."""
    return 100.0 + 0.03 * xy[:, 1]


def test_corner_ground_follows_the_final_pose_not_the_stale_plane():
    """Stage 2 fitted the image's ground plane at its own pose; the bundle
    then moved the camera (here: the plane is 30 m off the block's datum).
    The corners' ground is where the matched segments' bottoms meet their
    verticals through the FINAL pose; an unmatched corner the plane through
    the measured ones."""
    cam = Camera("PINHOLE", 2000, 1500, [1500.0, 1500.0, 1000.0, 750.0], 1)
    s = np.sqrt(0.5)  # looking north, 45 deg down
    R = np.array([[1.0, 0.0, 0.0], [0.0, -s, -s], [0.0, s, -s]])
    pose = Pose.from_center(R, np.array([0.0, -60.0, 160.0]))
    corner_xy = np.array(
        [[-15.0, 0.0], [10.0, 5.0], [-5.0, 30.0], [12.0, 35.0], [0, 20.0]]
    )
    matched = np.arange(4)  # corner 4 is seen but not matched
    foot = np.column_stack([corner_xy[matched], _ground(corner_xy[matched])])
    top = foot + [0.0, 0.0, 4.0]
    seg = np.stack(
        [cam.img_from_cam(pose.transform(top)), cam.img_from_cam(pose.transform(foot))],
        axis=1,
    )  # (K, 2, 2) px, no distortion: raw = undistorted
    registration = SimpleNamespace(
        inlier_pairs=np.column_stack([matched, np.arange(4)]), inlier_segments_px=seg
    )
    inputs = SimpleNamespace(
        cadastre=SimpleNamespace(corner_xy=corner_xy),
        priors=SimpleNamespace(
            cameras={1: cam}, images={7: SimpleNamespace(camera_id=1)}
        ),
    )
    block = Block({1: cam}, {7: ImageRecord(7, "N_00.jpg", 1, pose)})
    stale = np.array([0.0, 0.03, 130.0])  # z = 0.03 y + 130: 30 m up
    state = SimpleNamespace(planes={7: stale})
    outcomes = {7: SimpleNamespace(image_id=7, registration=registration)}

    planes, corners, heights = _rebased_planes(inputs, block, state, outcomes)
    seen = np.ones((len(corner_xy), 1), bool)
    z = _corner_ground(corner_xy, planes, corners, heights, seen)

    np.testing.assert_allclose(z[:4], _ground(corner_xy[:4]), atol=1e-6)
    # the unmatched corner: the plane through the measured ones (a 1 m^2
    # ridge on its slopes)
    np.testing.assert_allclose(z[4], _ground(corner_xy[4:])[0], atol=1e-3)


def test_facade_points_are_observed_on_their_segments_kept_by_the_bundle():
    """A facade track's point is observed on the line of the segment that
    measured it (moved across from its projection, so its reprojection
    error is the line residual), in the images the output keeps, only for
    the observations the last solve kept, and once per image (the nearer of
    two segments of one track)."""
    from obliq_colmap.pipeline.output import _facade_observations

    cam = Camera("PINHOLE", 2000, 1500, [1500.0, 1500.0, 1000.0, 750.0], 1)
    s = np.sqrt(0.5)
    R = np.array([[1.0, 0.0, 0.0], [0.0, -s, -s], [0.0, s, -s]])
    poses = [Pose.from_center(R, np.array([x, -60.0, 160.0])) for x in (0.0, 20.0)]
    block = Block(
        {1: cam},
        {i + 1: ImageRecord(i + 1, f"{i}.jpg", 1, p) for i, p in enumerate(poses)},
    )
    F = np.array([[0.0, 10.0, 108.0], [5.0, 12.0, 104.0]])  # two tracks
    # observations (image index, track): the second image holds track 0
    # twice (the first segment 2 px off, the second 0.5 px) and track 1 once
    image = np.array([0, 0, 1, 1, 1])
    track = np.array([0, 1, 0, 0, 1])
    offset = np.array([0.3, -0.4, 2.0, 0.5, 0.7])  # px, across the segment
    ends = np.zeros((5, 2, 2))
    for h in range(5):
        p = cam.img_from_cam(poses[image[h]].transform(F[track[h]][None]))[0]
        ends[h] = [p + [-20.0, 1.0 + offset[h]], p + [20.0, -1.0 + offset[h]]]
    tracks = SimpleNamespace(image=image, track=track, num_observations=5)
    stage3 = SimpleNamespace(
        ids=(1, 2),
        tracks=tracks,
        ends_raw=ends,
        kept_observations=np.array([0, 2, 3, 4]),  # obs 1: an outlier
    )
    fobs = _facade_observations(block, stage3, F)

    assert [i for i, _ in fobs[0]] == [1, 2] and [i for i, _ in fobs[1]] == [2]
    for j, h_of in ((0, {1: 0, 2: 3}), (1, {2: 4})):
        for i, xy in fobs[j]:
            h = h_of[i]
            d = ends[h, 1] - ends[h, 0]
            n = np.array([-d[1], d[0]]) / np.linalg.norm(d)
            assert abs(np.dot(xy - ends[h, 0], n)) < 1e-9  # on the segment's line
            proj = cam.img_from_cam(poses[i - 1].transform(F[j][None]))[0]
            # moved straight across from the projection, by the residual
            assert abs(abs(np.dot(xy - proj, n)) - np.linalg.norm(xy - proj)) < 1e-9
            assert 0.1 < np.linalg.norm(xy - proj) < 1.0
