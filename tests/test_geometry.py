"""Camera models, poses and homogeneous helpers against pycolmap and exact cases."""

import numpy as np
import pycolmap
import pytest

from obliq_colmap import geometry as g

MODELS = {
    "SIMPLE_PINHOLE": [1000.0, 500.0, 400.0],
    "PINHOLE": [1000.0, 1010.0, 503.0, 397.0],
    "SIMPLE_RADIAL": [1000.0, 500.0, 400.0, -0.08],
    "RADIAL": [1000.0, 500.0, 400.0, -0.08, 0.02],
    "OPENCV": [1000.0, 1010.0, 500.0, 400.0, -0.08, 0.02, 1e-3, -2e-3],
}


def random_points_cam(rng, n=200):
    X = rng.uniform(-0.6, 0.6, size=(n, 3))
    X[:, 2] = rng.uniform(1.0, 50.0, size=n)
    X[:, :2] *= X[:, 2:]
    return X


@pytest.mark.parametrize("model", list(MODELS))
def test_img_from_cam_matches_pycolmap(model):
    rng = np.random.default_rng(0)
    cam = g.Camera(model, 1000, 800, MODELS[model])
    X = random_points_cam(rng)
    ours = cam.img_from_cam(X)
    theirs = np.asarray(cam.to_pycolmap().img_from_cam(X))
    np.testing.assert_allclose(ours, theirs, atol=1e-9, rtol=0)


@pytest.mark.parametrize("model", list(MODELS))
def test_cam_from_img_inverts_distortion(model):
    rng = np.random.default_rng(1)
    cam = g.Camera(model, 1000, 800, MODELS[model])
    X = random_points_cam(rng)
    uv = cam.cam_from_img(cam.img_from_cam(X))
    np.testing.assert_allclose(uv, X[:, :2] / X[:, 2:], atol=1e-12, rtol=0)
    # Undistorted pixels are the pinhole projection with the same K.
    und = cam.undistort_pixels(cam.img_from_cam(X))
    pin = (X / X[:, 2:]) @ cam.K.T
    np.testing.assert_allclose(und, pin[:, :2], atol=1e-8, rtol=0)


@pytest.mark.parametrize("model", list(MODELS))
def test_no_pixels_undistort_to_no_pixels(model):
    # A registration with no inlier segment undistorts an empty set.
    cam = g.Camera(model, 1000, 800, MODELS[model])
    assert cam.undistort_pixels(np.zeros((0, 2))).shape == (0, 2)


def test_points_behind_camera_are_nan():
    cam = g.Camera("PINHOLE", 100, 100, [50, 50, 50, 50])
    xy = cam.img_from_cam(np.array([[0.0, 0.0, -1.0], [0.0, 0.0, 1.0]]))
    assert np.isnan(xy[0]).all() and np.allclose(xy[1], [50, 50])


def test_unsupported_model_is_rejected():
    with pytest.raises(ValueError, match="not supported"):
        g.Camera("FISHEYE", 10, 10, [1, 1, 1, 1])
    with pytest.raises(ValueError, match="params"):
        g.Camera("PINHOLE", 10, 10, [1, 1, 1])


def test_camera_pycolmap_round_trip():
    cam = g.Camera("OPENCV", 1000, 800, MODELS["OPENCV"], camera_id=7)
    back = g.Camera.from_pycolmap(cam.to_pycolmap())
    assert back.model == "OPENCV" and back.camera_id == 7
    np.testing.assert_array_equal(back.params, cam.params)


def test_rotations_are_orthonormal_and_round_trip():
    rng = np.random.default_rng(2)
    for _ in range(50):
        R = g.rotation_from_axis_angle(rng.normal(size=3) * 2)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.isclose(np.linalg.det(R), 1.0)
        q = g.quat_xyzw_from_rotation(R)
        np.testing.assert_allclose(g.rotation_from_quat_xyzw(q), R, atol=1e-12)
        # Same convention as pycolmap's Rotation3d.
        np.testing.assert_allclose(
            np.asarray(pycolmap.Rotation3d(q).matrix()), R, atol=1e-12
        )


def test_rotation_aligning_and_angle():
    rng = np.random.default_rng(3)
    for _ in range(20):
        a, b = rng.normal(size=3), rng.normal(size=3)
        R = g.rotation_aligning(a, b)
        np.testing.assert_allclose(
            R @ (a / np.linalg.norm(a)), b / np.linalg.norm(b), atol=1e-12
        )
    R = g.rotation_aligning([0, 0, 1.0], [0, 0, -1.0])
    np.testing.assert_allclose(R @ [0, 0, 1.0], [0, 0, -1.0], atol=1e-12)
    assert g.rotation_angle_deg(
        g.rotation_z(np.radians(3.0)), np.eye(3)
    ) == pytest.approx(3.0)


def test_pose_center_inverse_and_rigid3d():
    R = g.rotation_from_axis_angle([0.3, -0.2, 1.0])
    pose = g.Pose.from_center(R, [10.0, -5.0, 100.0])
    np.testing.assert_allclose(pose.center, [10.0, -5.0, 100.0], atol=1e-12)
    np.testing.assert_allclose(pose.transform(pose.center[None]), 0.0, atol=1e-12)
    X = np.array([[1.0, 2.0, 3.0]])
    np.testing.assert_allclose(
        pose.inverse().transform(pose.transform(X)), X, atol=1e-12
    )
    back = g.Pose.from_rigid3d(pose.to_rigid3d())
    np.testing.assert_allclose(back.rotation, R, atol=1e-12)
    np.testing.assert_allclose(back.translation, pose.translation, atol=1e-9)


def test_project_matches_pycolmap_image():
    cam = g.Camera("RADIAL", 1000, 800, MODELS["RADIAL"])
    pose = g.Pose.from_center(
        g.rotation_from_axis_angle([0.1, 0.2, 0.3]), [0, 0, -30.0]
    )
    X = np.array([[1.0, 2.0, 3.0], [-4.0, 1.0, 0.5]])
    xy, depth = g.project(cam, pose, X)
    expected = cam.to_pycolmap().img_from_cam(pose.transform(X))
    np.testing.assert_allclose(xy, expected, atol=1e-9)
    assert (depth > 0).all()


def test_lines_and_distances():
    p = np.array([[0.0, 0.0], [0.0, 0.0]])
    q = np.array([[10.0, 0.0], [0.0, 5.0]])
    lines = g.lines_through(p, q)
    np.testing.assert_allclose(np.linalg.norm(lines[:, :2], axis=1), 1.0)
    d = g.point_line_distance(np.array([[3.0, 2.0], [3.0, 2.0]]), lines)
    np.testing.assert_allclose(np.abs(d), [2.0, 3.0])


def test_rotation_angle_is_exact_and_vectorised():
    rng = np.random.default_rng(4)
    axes = rng.normal(size=(20, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = rng.uniform(0.0, np.pi, size=20)
    Rs = np.stack(
        [g.rotation_from_axis_angle(a * t) for a, t in zip(axes, angles, strict=False)]
    )
    out = g.rotation_angle_deg(Rs, np.broadcast_to(np.eye(3), Rs.shape))
    np.testing.assert_allclose(out, np.degrees(angles), atol=1e-9)
    # Small angles keep their precision (arccos of the trace would not).
    tiny = g.rotation_from_axis_angle([np.radians(1e-7), 0.0, 0.0])
    assert g.rotation_angle_deg(tiny, np.eye(3)) == pytest.approx(1e-7, rel=1e-6)
    assert g.rotation_angle_deg(Rs[0], Rs[0]) == 0.0


@pytest.mark.parametrize("model", sorted(g.SUPPORTED_MODELS))
def test_distort_pixels_inverts_undistort(model):
    full = [1500.0, 1490.0, 1000.0, 660.0, -0.08, 0.02, 1e-4, -2e-4]
    n_params = len(g.SUPPORTED_MODELS[model])
    params = {
        3: [1500.0, 1000.0, 660.0],
        4: full[:4] if model == "PINHOLE" else [1500.0, 1000.0, 660.0, -0.08],
        5: [1500.0, 1000.0, 660.0, -0.08, 0.02],
        8: full,
    }[n_params]
    cam = g.Camera(model, 2000, 1330, params)
    px = np.random.default_rng(0).uniform([0, 0], [2000, 1330], (50, 2))
    back = cam.distort_pixels(cam.undistort_pixels(px))
    assert np.abs(back - px).max() < 1e-6


def test_with_model_keeps_projection_where_models_overlap():
    cam = g.Camera("PINHOLE", 2000, 1330, [1500.0, 1500.0, 1003.0, 662.0])
    X = np.random.default_rng(1).normal([0, 0, 10], [3, 2, 1], (20, 3))
    for model in g.SUPPORTED_MODELS:
        other = cam.with_model(model)
        assert other.model == model and other.camera_id == cam.camera_id
        assert np.allclose(other.img_from_cam(X), cam.img_from_cam(X))
    with pytest.raises(ValueError, match="not supported"):
        cam.with_model("FISHEYE")
