"""The map projected onto an image: footprint edges at the image's ground
height, through a camera and a pose, drawn with a legend (:func:`draw_map`),
and the JPEG full-size / thumbnail pair the page links (:func:`write_overlay`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from obliq_colmap.geometry import Camera, Pose

__all__ = ["THUMB_WIDTH", "draw_map", "project_edges", "write_overlay"]

#: Thumbnail width (px) in the page's table.
THUMB_WIDTH = 240


def project_edges(
    edge_xy: np.ndarray, camera: Camera, pose: Pose, ground: float
) -> np.ndarray:
    """(E, 2, 2) pixels of (E, 2, 2) map edges at height ``ground`` (model
    frame); NaN where an end point is behind the camera."""
    xy = edge_xy.reshape(-1, 2)
    X = pose.transform(np.column_stack([xy, np.full(len(xy), ground)]))
    with np.errstate(divide="ignore", invalid="ignore"):
        px = camera.img_from_cam(X)
    px[X[:, 2] <= 0] = np.nan
    return px.reshape(-1, 2, 2)


def draw_map(
    image: np.ndarray,
    edges_px: np.ndarray,
    color: tuple[int, int, int],
    label: str | None,
) -> np.ndarray:
    """A copy of the (H, W, 3) BGR ``image`` with the (E, 2, 2) edges drawn in
    ``color`` (BGR) and a legend line ``label`` (if any) in the top-left
    corner; lines about 1 px per 600 px of image, at least 1."""
    import cv2

    out = image.copy()
    H, W = out.shape[:2]
    # far-off end points (grazing rays) would overflow cv2's fixed point
    limit = 4.0 * max(H, W)
    ok = np.all(np.isfinite(edges_px), axis=(1, 2)) & np.all(
        np.abs(edges_px) < limit, axis=(1, 2)
    )
    thickness = max(1, round(max(H, W) / 600))
    lines = np.round(edges_px[ok]).astype(np.int32)
    cv2.polylines(out, list(lines), False, color, thickness, cv2.LINE_AA)
    if label is None:
        return out
    scale = max(H, W) / 1600
    (tw, th), base = cv2.getTextSize(label, cv2.FONT_HERSHEY_SIMPLEX, scale, 2)
    pad = int(8 * scale) + 2
    cv2.rectangle(out, (0, 0), (tw + 2 * pad, th + base + 2 * pad), (0, 0, 0), -1)
    cv2.putText(
        out,
        label,
        (pad, pad + th),
        cv2.FONT_HERSHEY_SIMPLEX,
        scale,
        color,
        max(1, round(2 * scale)),
        cv2.LINE_AA,
    )
    return out


def write_overlay(
    image: np.ndarray,
    edges_px: np.ndarray,
    color: tuple[int, int, int],
    label: str,
    folder: Path,
    stem: str,
) -> tuple[str, str]:
    """Write ``stem.jpg`` (the full-size BGR ``image`` with the (E, 2, 2)
    edges and the legend, :func:`draw_map`) and ``stem_thumb.jpg``
    (THUMB_WIDTH px wide, the edges drawn on the reduced image so that they
    stay visible) under ``folder`` (inside the report's atomic folder);
    their names relative to it."""
    import cv2

    H, W = image.shape[:2]
    s = THUMB_WIDTH / W
    small = cv2.resize(image, (THUMB_WIDTH, max(1, round(H * s))), cv2.INTER_AREA)
    names = (f"{stem}.jpg", f"{stem}_thumb.jpg")
    drawn = (
        draw_map(image, edges_px, color, label),
        draw_map(small, edges_px * s, color, None),
    )
    for name, img, quality in zip(names, drawn, (90, 85), strict=True):
        ok, buf = cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_QUALITY, quality])
        if not ok:
            raise RuntimeError(f"JPEG encoding failed for {name}")
        (folder / name).write_bytes(buf.tobytes())
    return names
