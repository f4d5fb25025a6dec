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
