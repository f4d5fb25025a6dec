"""Reading images as COLMAP reads them, and saying why one cannot be used.

* The pixels as stored: an EXIF orientation tag is ignored, as COLMAP 3.8
  ignores it (OpenCV would turn the image, and its size would no longer
  match its camera).
* A JPEG cut short decodes without an error in OpenCV and pycolmap (the
  missing rows come out grey, and libjpeg's warning does not name the
  file), so it is detected explicitly: no end-of-image marker at the end.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

__all__ = ["IMAGE_EXTENSIONS", "image_problem", "read_image"]

#: Suffixes (lower case) of the image files a folder is searched for.
IMAGE_EXTENSIONS = frozenset({".jpg", ".jpeg", ".png", ".tif", ".tiff", ".bmp"})

# A JPEG ends with the end-of-image marker; some writers pad a few bytes after it.
_JPEG_START, _JPEG_END, _TAIL = b"\xff\xd8", b"\xff\xd9", 64


def image_problem(path: str | Path) -> str | None:
    """Why the file at ``path`` cannot be used as an image (in words), or None.

    Only what a decoder would hide: a truncated JPEG. An unreadable file is
    found by :func:`read_image` itself.
    """
    try:
        with open(path, "rb") as f:
            head = f.read(2)
            if head != _JPEG_START:
                return None
            f.seek(0, 2)
            size = f.tell()
            f.seek(max(0, size - _TAIL))
            tail = f.read()
    except OSError as exc:
        return f"cannot open ({exc.strerror or exc})"
    if _JPEG_END not in tail:
        return (
            f"truncated JPEG ({size} bytes, no end-of-image marker: its last rows"
            " would decode grey)"
        )
    return None


def read_image(path: str | Path, color: bool = False) -> tuple[np.ndarray | None, str]:
    """The image at ``path`` as stored ((H, W) uint8, or (H, W, 3) BGR with
    ``color``), or None and the reason it cannot be used."""
    import cv2

    problem = image_problem(path)
    if problem is not None:
        return None, problem
    flags = (cv2.IMREAD_COLOR if color else cv2.IMREAD_GRAYSCALE) | (
        cv2.IMREAD_IGNORE_ORIENTATION
    )
    img = cv2.imread(str(path), flags)
    if img is None:
        return None, "cannot read image (not a format OpenCV reads, or corrupt)"
    return img, ""
