"""Read priors in any supported format into a :class:`Block` in the map frame.

The format is recognised by content: a folder holding a COLMAP model, a
SQLite file (COLMAP database), or a text file by its first line (see
:mod:`obliq_colmap.priors.text`).
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from obliq_colmap.colmap_io import MODEL_FILES, Block, ImageRecord
from obliq_colmap.colmap_io import read_priors as read_model_priors
from obliq_colmap.errors import InputError
from obliq_colmap.geometry import Camera, Pose
from obliq_colmap.priors.cameras import camera_source
from obliq_colmap.priors.crs import to_map_crs
from obliq_colmap.priors.database import SQLITE_MAGIC, read_database
from obliq_colmap.priors.exif import has_xmp_priors, read_xmp_folder
from obliq_colmap.priors.opk import FLIP_YZ, cam_from_world_from_opk
from obliq_colmap.priors.options import PriorsOptions
from obliq_colmap.priors.text import read_geo, read_opk, sniff_text

logger = logging.getLogger(__name__)

#: Placeholder rotation of position-only priors: nadir, image top to grid north.
NADIR = FLIP_YZ


def prior_format(path: str | Path) -> str:
    """``"model"``, ``"xmp"`` (images with drone tags), ``"database"``,
    ``"opk"`` or ``"geo"``; InputError otherwise."""
    path = Path(path)
    if not path.exists():
        raise InputError(path, "priors path does not exist")
    if path.is_dir():
        if any((path / f"{MODEL_FILES[0]}{e}").is_file() for e in (".bin", ".txt")):
            return "model"
        if has_xmp_priors(path):
            return "xmp"
        raise InputError(
            path,
            "folder holding neither a COLMAP model (cameras, images, points3D) "
            "nor images with drone-dji GPS tags",
        )
    with path.open("rb") as f:
        head = f.read(4096)
    if head.startswith(SQLITE_MAGIC):
        return "database"
    text = head.decode("utf-8", errors="replace")
    first = next((line for line in text.splitlines() if line.strip()), "")
    kind = sniff_text(path, first)
    if kind is None:
        raise InputError(
            path,
            "unknown prior format: expected a COLMAP model folder, a COLMAP "
            "database, an 'image_name X Y Z omega phi kappa' file or ODM's geo.txt "
            f"(first line {first[:60]!r})",
        )
    return kind


def _check_images(block: Block, image_path: Path | None, source: Path) -> None:
    if image_path is None:
        return
    if not image_path.is_dir():
        raise InputError(image_path, "image folder does not exist")
    missing = [
        im.name for im in block.images.values() if not (image_path / im.name).is_file()
    ]
    if missing:
        shown = ", ".join(missing[:5]) + (" ..." if len(missing) > 5 else "")
        raise InputError(
            image_path,
            f"{len(missing)} image(s) of the priors {source} have no file "
            f"here: {shown}",
        )


def build_block(
    names: list[str],
    camera_ids: list[int],
    cameras: dict[int, Camera],
    centres: np.ndarray,
    rotations: np.ndarray,
) -> Block:
    """A Block from N names, camera ids, (N, 3) centres and (N, 3, 3) cam_from_world."""
    images = {
        i + 1: ImageRecord(i + 1, name, cid, Pose.from_center(R, c))
        for i, (name, cid, c, R) in enumerate(
            zip(names, camera_ids, centres, rotations, strict=True)
        )
    }
    used = {cid: cameras[cid] for cid in sorted(set(camera_ids))}
    return Block(used, images)


def read_priors(
    input_path: str | Path,
    image_path: str | Path | None = None,
    options: PriorsOptions | None = None,
) -> Block:
    """Read priors of any supported format; poses in the map frame.

    Raises
    ------
    InputError
        Unknown format, unreadable file, no intrinsics, images without a file,
        or a position-only format while ``options.require_rotation``.
    """
    options = options or PriorsOptions()
    path = Path(input_path)
    image_path = None if image_path is None else Path(image_path)
    kind = prior_format(path)
    if kind == "model":
        return read_model_priors(path, image_path)
    fallback = None
    if kind == "xmp":
        data = read_xmp_folder(path)
        names, xyz, crs, rotations = data.names, data.xyz, "EPSG:4326", data.rotations
    elif kind == "database":
        data = read_database(path)
        names, xyz, crs, rotations = data.names, data.xyz, data.crs, None
        fallback = data.cameras
    else:
        text = path.read_text(encoding="utf-8", errors="replace")
        data = read_opk(path, text) if kind == "opk" else read_geo(path, text)
        names, xyz, crs = data.names, data.xyz, data.crs
        rotations = (
            None if data.opk_deg is None else cam_from_world_from_opk(data.opk_deg)
        )
    if rotations is None:
        if options.require_rotation:
            raise InputError(
                path,
                f"{kind} priors give camera positions only; the registration needs "
                "a rotation prior within a few degrees (an OPK file or a COLMAP "
                "model), or `register --heading_step DEG` to search the headings",
            )
        logger.warning("%s: positions only; rotations set to nadir", path)
        rotations = np.broadcast_to(NADIR, (len(names), 3, 3))
    if crs is not None:
        xyz, _ = to_map_crs(xyz, crs, options.crs, path)
    cameras, camera_ids = camera_source(options, names, image_path, path, fallback)
    if not camera_ids:
        camera_ids = data.camera_ids
    block = build_block(names, camera_ids, cameras, xyz, rotations)
    _check_images(block, image_path, path)
    logger.info("%s: %d %s priors", path, len(block.images), kind)
    return block
