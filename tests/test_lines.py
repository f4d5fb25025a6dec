"""Segment detection: the COLMAP half-pixel convention, polarity, resolution."""

import cv2
import numpy as np
import pytest

from obliq_colmap.geometry import Camera
from obliq_colmap.lines import (
    LineOptions,
    RefineOptions,
    Segments,
    connected_pairs,
    detect_segments,
    lsd_available,
    merge_collinear,
    refine_segments,
)

DETECTORS = ["canny"] + (["lsd"] if lsd_available() else [])


def step_image(width, height, edge_x, dark=60, bright=190, supersample=8):
    """Vertical step edge at COLMAP x = edge_x (exact by area supersampling)."""
    hi = np.full((height * supersample, width * supersample), dark, np.uint8)
    # Hi-res pixel column c covers COLMAP [c, c + 1) / supersample.
    hi[:, int(round(edge_x * supersample)) :] = bright
    return cv2.resize(hi, (width, height), interpolation=cv2.INTER_AREA)


@pytest.mark.parametrize("detector", DETECTORS)
@pytest.mark.parametrize("edge_x", [100.0, 100.5, 100.25])
def test_half_pixel_convention(detector, edge_x):
    img = cv2.GaussianBlur(step_image(200, 160, edge_x), (0, 0), 0.8)
    segs = detect_segments(img, LineOptions(detector=detector, lsd_scale=1.0))
    assert len(segs) == 1
    x = segs.endpoints[0, :, 0]
    # Sub-pixel: well inside the 0.5 px of the integer-centre convention.
    np.testing.assert_allclose(x, edge_x, atol=0.08)
    assert segs.lengths[0] > 140


@pytest.mark.parametrize("detector", DETECTORS)
def test_polarity_and_strength(detector):
    img = cv2.GaussianBlur(step_image(200, 160, 100.0, 60, 190), (0, 0), 0.8)
    segs = detect_segments(img, LineOptions(detector=detector))
    # Bright on the right: the normal points to +x.
    np.testing.assert_allclose(segs.normal[0], [1.0, 0.0], atol=1e-3)
    # A blurred 130-grey step: the peak gradient is a good part of it.
    assert 20.0 < segs.strength[0] <= 130.0
    flipped = detect_segments(255 - img, LineOptions(detector=detector))
    np.testing.assert_allclose(flipped.normal[0], [-1.0, 0.0], atol=1e-3)


def test_lsd_default_scale_is_corrected():
    """LSD's Gaussian sub-sampling (scale 0.8) shifts by 0.5/scale, not 0.5."""
    if not lsd_available():
        pytest.skip("OpenCV without LSD")
    img = cv2.GaussianBlur(step_image(200, 160, 100.0), (0, 0), 0.8)
    segs = detect_segments(img, LineOptions(detector="lsd", lsd_scale=0.8))
    np.testing.assert_allclose(segs.endpoints[0, :, 0], 100.0, atol=0.1)


@pytest.mark.parametrize("detector", DETECTORS)
def test_reduced_resolution_returns_full_resolution_pixels(detector):
    img = cv2.GaussianBlur(step_image(1600, 1200, 801.0, supersample=2), (0, 0), 1.0)
    segs = detect_segments(
        img, LineOptions(detector=detector, max_image_size_px=400, lsd_scale=1.0)
    )
    assert len(segs) >= 1
    longest = np.argmax(segs.lengths)
    # Detection at 1/4 resolution: within a quarter of a detection pixel.
    np.testing.assert_allclose(segs.endpoints[longest, :, 0], 801.0, atol=1.0)
    assert segs.lengths[longest] > 1000
    # The endpoints' noise unit: 4 full-resolution pixels per detection pixel,
    # kept by the set's operations.
    assert segs.pixel_scale == pytest.approx(4.0)
    assert segs.subset([longest]).pixel_scale == pytest.approx(4.0)
    assert Segments.concatenate([segs, Segments()]).pixel_scale == pytest.approx(4.0)
    full = detect_segments(img, LineOptions(detector=detector, max_image_size_px=None))
    assert full.pixel_scale == 1.0


def test_slanted_edge_subpixel():
    """A slanted anti-aliased edge: endpoints within 0.1 px of the true line."""
    W, H, ss = 300, 240, 8
    hi = np.full((H * ss, W * ss), 50, np.uint8)
    p0, p1 = np.array([120.3, 10.0]), np.array([170.9, 230.0])  # COLMAP
    poly = np.array([p0, p1, [W, H], [W, 0]]) * ss - 0.5
    cv2.fillPoly(hi, [np.round(poly * 16).astype(np.int32)], 200, shift=4)
    img = cv2.resize(hi, (W, H), interpolation=cv2.INTER_AREA)
    for detector in DETECTORS:
        segs = detect_segments(img, LineOptions(detector=detector, lsd_scale=1.0))
        k = np.argmax(segs.lengths)
        d = p1 - p0
        n = np.array([d[1], -d[0]]) / np.linalg.norm(d)
        dist = (segs.endpoints[k] - p0) @ n
        assert np.abs(dist).max() < 0.1, (detector, dist)


def test_structure_free_images_give_few_short_segments():
    rng = np.random.default_rng(0)
    ramp = np.tile(np.linspace(0, 255, 640), (480, 1)).astype(np.uint8)
    segs = detect_segments(ramp)
    assert len(segs) == 0
    flat = np.full((480, 640), 128, np.uint8)
    assert len(detect_segments(flat)) == 0
    noise = rng.normal(128, 20, (480, 640)).clip(0, 255).astype(np.uint8)
    segs = detect_segments(noise)
    assert len(segs) == 0 or np.median(segs.lengths) < 20


def test_merge_collinear_joins_pieces_only():
    ends = np.array(
        [
            [[10.0, 10.0], [10.0, 50.0]],
            [[10.3, 55.0], [10.3, 100.0]],  # same line, gap 5 px
            [[30.0, 10.0], [30.0, 100.0]],  # parallel, 20 px away
            [[10.0, 200.0], [10.0, 240.0]],  # same line, gap 100 px
        ]
    )
    normal = np.tile([1.0, 0.0], (4, 1))
    merged = merge_collinear(Segments(ends, normal, np.ones(4)), max_gap_px=10)
    assert len(merged) == 3
    k = np.argmax(merged.lengths)
    assert merged.lengths[k] == pytest.approx(90.0, abs=0.5)
    # Opposite polarity never merges.
    normal[1] = [-1.0, 0.0]
    assert len(merge_collinear(Segments(ends, normal, np.ones(4)))) == 4


def test_connected_pairs():
    count, group = connected_pairs(6, np.array([0, 4, 2]), np.array([4, 5, 3]))
    assert count == 3
    assert group[0] == group[4] == group[5] != group[2] == group[3] != group[1]


def test_bad_image_shape():
    with pytest.raises(ValueError, match="shape"):
        detect_segments(np.zeros((4, 4, 4, 4), np.uint8))
    with pytest.raises(ValueError, match="detector"):
        LineOptions(detector="hough")


def blurred_edge(xy, p0, p1, blur, dark=50.0, bright=200.0):
    """Intensities at (N, 2) points of a Gaussian-blurred step along p0-p1
    (bright on the left of p0 -> p1), COLMAP pixels."""
    from scipy.special import ndtr

    d = (p1 - p0) / np.linalg.norm(p1 - p0)
    left = np.array([d[1], -d[0]])
    return dark + (bright - dark) * ndtr(((xy - p0) @ left) / blur)


def pixel_grid(W, H):
    x, y = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    return np.column_stack([x.ravel(), y.ravel()])


@pytest.mark.parametrize("noise", [0.0, 4.0])
def test_refine_segments_moves_a_segment_onto_its_edge(noise):
    """A segment 0.4 px off and tilted comes back onto the edge, to within the
    noise's share: a profile's edge error is noise / slope at the crossing
    (slope = contrast / (sqrt(2 pi) blur)), averaged over ~200 profiles."""
    W, H, blur = 240, 260, 1.0
    p0, p1 = np.array([100.3, 20.0]), np.array([140.9, 240.0])
    img = blurred_edge(pixel_grid(W, H), p0, p1, blur).reshape(H, W)
    img += np.random.default_rng(1).normal(0.0, noise, img.shape)
    img = np.clip(np.round(img), 0, 255).astype(np.uint8)
    d = (p1 - p0) / np.linalg.norm(p1 - p0)
    left = np.array([d[1], -d[0]])
    start = np.array([p0 + 0.4 * left, p1 - 0.2 * left])  # LSD-sized errors
    segs = Segments(start[None], left[None], [100.0])  # bright side
    options = RefineOptions()
    out = refine_segments(img, segs, options=options)
    dist = (out.endpoints[0] - p0) @ left
    slope = 150.0 / (np.sqrt(2 * np.pi) * blur)
    sigma_line = (noise + 0.3) / slope / np.sqrt(200)  # + rounding to grey levels
    # an endpoint of a line fit: ~2 sigma of the offset (6 sigma bound); the
    # start's offset shrinks ~2.3x per round (the near plateau's pull)
    remainder = 0.4 / 2.3**options.rounds
    assert np.abs(dist).max() < 6 * 2 * sigma_line + remainder, dist
    # the endpoints keep their place along the segment (each round moves
    # them across the previous one's direction)
    np.testing.assert_allclose((out.endpoints[0] - start) @ d, 0.0, atol=0.01)
    np.testing.assert_array_equal(out.normal, segs.normal)


def test_refine_segments_keeps_segments_without_an_edge():
    img = np.full((100, 100), 128, np.uint8)
    segs = Segments(np.array([[[20.0, 50.0], [80.0, 50.0]]]), [[0.0, 1.0]], [10.0])
    out = refine_segments(img, segs)
    np.testing.assert_array_equal(out.endpoints, segs.endpoints)
    assert len(refine_segments(img, Segments())) == 0


def test_refine_segments_samples_through_the_lens():
    """Segments in undistorted pixels of a camera with radial distortion are
    refitted on the raw image: straight in undistorted pixels, curved in raw."""
    W, H = 400, 300
    cam = Camera("SIMPLE_RADIAL", W, H, [300.0, 200.0, 150.0, -0.15])
    p0, p1 = np.array([40.0, 30.0]), np.array([370.0, 60.0])  # undistorted
    raw = pixel_grid(W, H)
    img = blurred_edge(cam.undistort_pixels(raw), p0, p1, 1.0).reshape(H, W)
    img = np.round(img).astype(np.uint8)
    d = (p1 - p0) / np.linalg.norm(p1 - p0)
    left = np.array([d[1], -d[0]])
    start = np.array([p0 + 0.6 * left, p1 - 0.4 * left])
    segs = Segments(start[None], left[None], [100.0])
    through = refine_segments(img, segs, cam).endpoints[0]
    assert np.abs((through - p0) @ left).max() < 0.05
    # without the lens the profiles miss the curved edge: worse or refused
    plain = refine_segments(img, segs).endpoints[0]
    assert np.abs((plain - p0) @ left).max() > 0.1


def test_refine_options_are_checked():
    with pytest.raises(ValueError):
        RefineOptions(step_px=3.0, radius_px=2.0)


def test_refine_segments_reach_follows_the_detection_scale():
    """Segments detected at half resolution (pixel_scale 2) carry errors in
    pixels of that image: the profile and the largest move scale with it."""
    W, H, blur = 240, 260, 1.0
    p0, p1 = np.array([100.3, 20.0]), np.array([140.9, 240.0])
    img = blurred_edge(pixel_grid(W, H), p0, p1, blur).reshape(H, W)
    img = np.round(img).astype(np.uint8)
    d = (p1 - p0) / np.linalg.norm(p1 - p0)
    left = np.array([d[1], -d[0]])
    start = np.array([p0 + 2.8 * left, p1 + 2.8 * left])  # > max_move_px 1.5
    options = RefineOptions()
    error = {}
    for scale in (1.0, 2.0):
        segs = Segments(start[None], left[None], [100.0], pixel_scale=scale)
        out = refine_segments(img, segs, options=options).endpoints[0]
        error[scale] = np.abs((out - p0) @ left).max()
    assert error[1.0] > 1.0  # out of reach: at most 1.5 px moved
    # in reach; the start's offset shrinks ~2.3x per round (noise-free image)
    assert error[2.0] < 2.8 / 2.3**options.rounds
