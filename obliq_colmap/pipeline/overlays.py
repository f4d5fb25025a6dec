"""The overlays a user looks at: the map drawn through each WRITTEN image's
final pose (after the bundle), with a legend (:func:`final_overlays`). The
per-stage overlays (after stage 2, also for images the bundle then leaves
out) go to a ``stage2/`` subfolder for diagnosis.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from obliq_colmap.colmap_io import Block
from obliq_colmap.images import read_image
from obliq_colmap.report.overlays import draw_map, project_edges
from obliq_colmap.state import BlockState, ImageOutcome, Inputs

__all__ = ["STAGE2_FOLDER", "final_overlays"]

logger = logging.getLogger(__name__)

#: Subfolder of ``--overlay_path`` for the overlays drawn after stage 2.
STAGE2_FOLDER = "stage2"

_GREEN = (60, 220, 60)  # BGR


def _image_ground(
    state: BlockState, outcome: ImageOutcome, corner_xy: np.ndarray
) -> float:
    """The image's ground height (m, local frame): its plane at the map
    corners it registered on (at all corners when it has none)."""
    r = outcome.registration
    used = (
        r.inlier_pairs[:, 0] if r is not None and len(r.inlier_pairs) else slice(None)
    )
    return float(np.median(state.ground(outcome.image_id)(corner_xy[used])))


def final_overlays(
    inputs: Inputs,
    block: Block,
    state: BlockState,
    outcomes: dict[int, ImageOutcome],
    folder: Path,
    stage: str,
) -> list[Path]:
    """Write ``<image name>.jpg`` under ``folder`` for every image of
    ``block`` (the written ones, LOCAL frame before the output's height
    shift): the map's edges at the image's ground through its final camera,
    in green, and a legend naming the pose drawn (``stage``)."""
    import cv2

    cad = inputs.cadastre
    written = []
    for i, im in sorted(block.images.items()):
        image, problem = read_image(inputs.image_path / im.name, color=True)
        if image is None:
            logger.warning("%s: no overlay (%s)", im.name, problem)
            continue
        camera = block.cameras[im.camera_id]
        ground = _image_ground(state, outcomes[i], cad.corner_xy)
        px = project_edges(cad.edge_xy, camera, im.cam_from_world, ground)
        label = f"{im.name}: map footprints through the {stage} pose"
        path = folder / Path(im.name.replace("/", "__")).with_suffix(".jpg").name
        ok, buf = cv2.imencode(
            ".jpg", draw_map(image, px, _GREEN, label), [cv2.IMWRITE_JPEG_QUALITY, 90]
        )
        if ok:
            path.write_bytes(buf.tobytes())
            written.append(path)
    return written
