"""Segment detection: the COLMAP half-pixel convention, polarity, resolution."""

import cv2
import numpy as np
import pytest

from obliq_colmap.lines import (
    LineOptions,
    Segments,
    connected_pairs,
    detect_segments,
    lsd_available,
    merge_collinear,
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
