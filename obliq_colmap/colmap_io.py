"""Read a priors model and write a result model, the COLMAP way.

The priors are a COLMAP model folder (binary or text) with rough poses in the
map's absolute frame. The result is written in a LOCAL frame,
``world_abs = model_xyz + origin`` (no rotation), so that float32 consumers
(MVS on a GPU) keep their precision; the origin and the CRS go into
``georef.json`` beside the model files. Writing is atomic: everything goes into
a temporary sibling folder that is renamed into place at the end, so a failed
run never leaves a model that looks complete.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from obliq_colmap.errors import InputError
from obliq_colmap.files import AtomicFolder
from obliq_colmap.geometry import SUPPORTED_MODELS, Camera, Pose

logger = logging.getLogger(__name__)

MODEL_FILES = ("cameras", "images", "points3D")
GEOREF_FILE = "georef.json"


@dataclass
class ImageRecord:
    """One image of a block.

    Attributes
    ----------
    image_id : int, COLMAP image id.
    name : str, file name relative to the image folder (as in COLMAP).
    camera_id : int, the physical camera (shared by the images of one head).
    cam_from_world : Pose, in the frame of the block it belongs to.
    """

    image_id: int
    name: str
    camera_id: int
    cam_from_world: Pose


@dataclass
class Block:
    """Cameras and posed images: the plain-data view of a COLMAP model."""

    cameras: dict[int, Camera] = field(default_factory=dict)
    images: dict[int, ImageRecord] = field(default_factory=dict)

    def image_by_name(self, name: str) -> ImageRecord:
        for image in self.images.values():
            if image.name == name:
                return image
        raise KeyError(name)

    def shifted(self, origin: np.ndarray) -> Block:
        """The same block in the frame ``X_new = X_old - origin``.

        ``X_cam = R X_old + t = R (X_new + origin) + t``, so ``t_new = t + R origin``.
        """
        origin = np.asarray(origin, float)
        images = {
            i: ImageRecord(
                im.image_id,
                im.name,
                im.camera_id,
                Pose(
                    im.cam_from_world.rotation,
                    im.cam_from_world.translation + im.cam_from_world.rotation @ origin,
                ),
            )
            for i, im in self.images.items()
        }
        cameras = {
            i: Camera(c.model, c.width, c.height, c.params.copy(), c.camera_id)
            for i, c in self.cameras.items()
        }
        return Block(cameras, images)


@dataclass
class Point3D:
    """A 3D point with its track.

    Attributes
    ----------
    xyz : (3,) array, model (local) frame, metres.
    observations : list of (image_id, (2,) pixel array).
    color : (3,) uint8 RGB or None (written black).
    """

    xyz: np.ndarray
    observations: list[tuple[int, np.ndarray]]
    color: np.ndarray | None = None


@dataclass
class Georef:
    """Where a local model sits in the map: ``world_abs = model_xyz + origin``."""

    origin: np.ndarray
    crs: str | None = None
    extra: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        out = dict(self.extra)
        out.update(
            {
                "crs": self.crs,
                "origin": [float(v) for v in np.asarray(self.origin, float)],
                "transform": "world_abs = model_xyz + origin",
            }
        )
        return out


# --------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------


def _model_format(path: Path) -> str:
    for ext in (".bin", ".txt"):
        if all((path / f"{name}{ext}").is_file() for name in MODEL_FILES):
            return ext
    present = sorted(p.name for p in path.iterdir()) if path.is_dir() else []
    raise InputError(
        path,
        "not a COLMAP model: expected cameras, images and points3D as .bin or "
        f".txt, found {present or 'nothing'}",
    )


def read_model(path: str | Path) -> Block:
    """Read a COLMAP model folder (binary or text) into a :class:`Block`.

    Raises
    ------
    InputError
        Missing folder or files, unreadable model, unsupported camera model.
    """
    import pycolmap

    path = Path(path)
    if not path.exists():
        raise InputError(path, "model folder does not exist")
    if not path.is_dir():
        raise InputError(path, "expected a COLMAP model folder, got a file")
    _model_format(path)
    try:
        rec = pycolmap.Reconstruction(str(path))
    except Exception as exc:  # pycolmap raises generic errors on corrupt files
        raise InputError(path, f"cannot read the COLMAP model: {exc}") from None
    block = Block()
    for camera_id, cam in rec.cameras.items():
        model = cam.model.name
        if model not in SUPPORTED_MODELS:
            raise InputError(
                path,
                f"camera {camera_id} has model {model}; supported perspective "
                f"models: {', '.join(SUPPORTED_MODELS)}",
            )
        block.cameras[int(camera_id)] = Camera.from_pycolmap(cam)
    for image_id, image in rec.images.items():
        if not image.has_pose:
            logger.warning("%s: image %s has no pose; skipped", path, image.name)
            continue
        block.images[int(image_id)] = ImageRecord(
            int(image_id),
            image.name,
            int(image.camera_id),
            Pose.from_rigid3d(image.cam_from_world()),
        )
    if not block.images:
        raise InputError(path, "the model has no posed images")
    return block


def read_priors(input_path: str | Path, image_path: str | Path | None = None) -> Block:
    """Read the priors model and check that its images exist under ``image_path``.

    Raises
    ------
    InputError
        As :func:`read_model`, and when an image of the model has no file.
    """
    block = read_model(input_path)
    if image_path is not None:
        image_path = Path(image_path)
        if not image_path.is_dir():
            raise InputError(image_path, "image folder does not exist")
        missing = [
            im.name
            for im in block.images.values()
            if not (image_path / im.name).is_file()
        ]
        if missing:
            shown = ", ".join(missing[:5]) + (" ..." if len(missing) > 5 else "")
            raise InputError(
                image_path,
                f"{len(missing)} image(s) of the priors model {input_path} have no "
                f"file here: {shown}",
            )
    return block


def read_georef(model_path: str | Path) -> Georef:
    """Read ``georef.json`` of a result model; a model without one is absolute."""
    path = Path(model_path) / GEOREF_FILE
    if not path.is_file():
        return Georef(np.zeros(3), None)
    try:
        data = json.loads(path.read_text())
        origin = np.asarray(data["origin"], dtype=float).reshape(3)
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(path, f"invalid georef.json: {exc}") from None
    extra = {k: v for k, v in data.items() if k not in ("crs", "origin", "transform")}
    return Georef(origin, data.get("crs"), extra)


# --------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------


def to_reconstruction(block: Block, points3D: list[Point3D] | None = None):
    """Build a ``pycolmap.Reconstruction`` (one trivial rig per camera)."""
    import pycolmap

    points3D = points3D or []
    rec = pycolmap.Reconstruction()
    for camera in block.cameras.values():
        rec.add_camera_with_trivial_rig(camera.to_pycolmap())
    # Collect each image's observations; point2D index = position in its list.
    obs_per_image: dict[int, list[np.ndarray]] = {i: [] for i in block.images}
    track_elements: list[list[tuple[int, int]]] = []
    for point in points3D:
        elements = []
        for image_id, xy in point.observations:
            if image_id not in obs_per_image:
                raise ValueError(f"point observed in unknown image {image_id}")
            elements.append((image_id, len(obs_per_image[image_id])))
            obs_per_image[image_id].append(np.asarray(xy, float).reshape(2))
        track_elements.append(elements)
    for image in block.images.values():
        im = pycolmap.Image(
            name=image.name, camera_id=image.camera_id, image_id=image.image_id
        )
        im.points2D = pycolmap.Point2DList(
            [pycolmap.Point2D(xy) for xy in obs_per_image[image.image_id]]
        )
        rec.add_image_with_trivial_frame(im, image.cam_from_world.to_rigid3d())
    for point, elements in zip(points3D, track_elements, strict=False):
        if len(elements) == 0:
            continue
        track = pycolmap.Track()
        for image_id, idx in elements:
            track.add_element(image_id, idx)
        color = np.zeros(3, np.uint8) if point.color is None else point.color
        rec.add_point3D(
            np.asarray(point.xyz, float), track, np.asarray(color, np.uint8)
        )
    # each point's error: the mean distance of its observations to its
    # projections (COLMAP's model_analyzer reports their mean)
    rec.update_point_3d_errors()
    return rec


def write_model_files(
    folder: Path, block: Block, points3D: list[Point3D] | None, georef: Georef
) -> None:
    """Write the binary model files and georef.json into an existing folder."""
    rec = to_reconstruction(block, points3D)
    rec.write_binary(str(folder))
    (folder / GEOREF_FILE).write_text(json.dumps(georef.to_json(), indent=2) + "\n")


def write_result(
    output_path: str | Path,
    block: Block,
    georef: Georef,
    points3D: list[Point3D] | None = None,
    extra_files: dict[str, str] | None = None,
) -> Path:
    """Write a result model atomically: model files + georef.json (+ extra files).

    Parameters
    ----------
    output_path : the model folder; must not exist or be empty.
    block : cameras and images, poses in the LOCAL frame of ``georef``.
    points3D : constrained points with tracks, local frame.
    extra_files : file name -> text content written beside the model
        (e.g. the JSON run report).
    """
    with AtomicFolder(output_path) as tmp:
        write_model_files(tmp, block, points3D, georef)
        for name, text in (extra_files or {}).items():
            (tmp / name).write_text(text)
    return Path(output_path)


def write_absolute_model(output_path: str | Path, block: Block) -> Path:
    """Write a model in absolute coordinates (priors, ground truth), atomically."""
    with AtomicFolder(output_path) as tmp:
        to_reconstruction(block).write_binary(str(tmp))
    return Path(output_path)
