"""Images read as COLMAP reads them: stored pixels, truncated JPEGs named."""

from __future__ import annotations

import struct

import cv2
import numpy as np

from obliq_colmap.images import image_problem, read_image


def _jpeg(h=60, w=90) -> bytes:
    rng = np.random.default_rng(0)
    img = (rng.random((h, w)) * 255).astype(np.uint8)
    ok, buf = cv2.imencode(".jpg", img)
    assert ok
    return buf.tobytes()


def _with_exif_orientation(jpeg: bytes, orientation: int) -> bytes:
    """The JPEG with an APP1 Exif segment holding one tag: Orientation."""
    ifd = struct.pack("<H", 1) + struct.pack("<HHIHH", 0x0112, 3, 1, orientation, 0)
    tiff = b"II*\x00" + struct.pack("<I", 8) + ifd + struct.pack("<I", 0)
    payload = b"Exif\x00\x00" + tiff
    app1 = b"\xff\xe1" + struct.pack(">H", len(payload) + 2) + payload
    return jpeg[:2] + app1 + jpeg[2:]


def test_a_complete_jpeg_reads_and_a_truncated_one_is_named(tmp_path):
    data = _jpeg()
    good = tmp_path / "good.jpg"
    good.write_bytes(data)
    img, problem = read_image(good)
    assert img is not None and img.shape == (60, 90) and problem == ""
    padded = tmp_path / "padded.jpg"  # some writers pad after the end marker
    padded.write_bytes(data + b"\x00" * 16)
    assert image_problem(padded) is None
    cut = tmp_path / "cut.jpg"
    cut.write_bytes(data[: int(0.4 * len(data))])
    # OpenCV decodes it without an error (grey rows) ...
    assert cv2.imread(str(cut), cv2.IMREAD_GRAYSCALE) is not None
    # ... so it is caught before decoding.
    img, problem = read_image(cut)
    assert img is None and "truncated JPEG" in problem


def test_exif_orientation_is_ignored_as_colmap_does(tmp_path):
    path = tmp_path / "turned.jpg"
    path.write_bytes(_with_exif_orientation(_jpeg(60, 90), 6))  # "rotate 90 CW"
    assert cv2.imread(str(path), cv2.IMREAD_GRAYSCALE).shape == (90, 60)
    img, problem = read_image(path)
    assert problem == "" and img.shape == (60, 90)
    color, _ = read_image(path, color=True)
    assert color.shape == (60, 90, 3)


def test_a_file_that_is_not_an_image_says_so(tmp_path):
    path = tmp_path / "notes.jpg"
    path.write_text("not an image")
    img, problem = read_image(path)
    assert img is None and "cannot read image" in problem
    img, problem = read_image(tmp_path / "missing.jpg")
    assert img is None and problem
