"""Intrinsics for prior formats that carry none (OPK text, geo.txt)."""

from __future__ import annotations

import sqlite3
from pathlib import Path

import numpy as np

from obliq_colmap.errors import InputError
from obliq_colmap.geometry import SUPPORTED_MODELS, Camera
from obliq_colmap.priors.options import PriorsOptions

#: parameter count -> COLMAP model when --camera_params names none.
_MODEL_BY_COUNT = {3: "SIMPLE_PINHOLE", 4: "SIMPLE_RADIAL", 5: "RADIAL", 8: "OPENCV"}


def parse_camera_params(text: str, width: int, height: int) -> Camera:
    """``[MODEL:]p1,p2,...`` (COLMAP order, pixels) into a Camera."""
    model, _, values = text.rpartition(":")
    try:
        params = [float(v) for v in values.split(",")]
    except ValueError:
        params = []
    model = model.strip().upper() or _MODEL_BY_COUNT.get(len(params), "")
    if model not in SUPPORTED_MODELS or not params:
        raise InputError(
            None,
            f"--camera_params must be [MODEL:]p1,p2,... in COLMAP's order for one "
            f"of {', '.join(SUPPORTED_MODELS)}, got {text!r}",
        )
    try:
        return Camera(model, width, height, np.asarray(params), 1)
    except ValueError as exc:
        raise InputError(None, f"--camera_params {text!r}: {exc}") from None


def _image_size(image_path: Path | None, names: list[str]) -> tuple[int, int]:
    """(width, height) of the first readable image, as stored (no EXIF turn)."""
    import cv2

    if image_path is None:
        raise InputError(None, "--camera_params needs --image_path to know the size")
    flags = cv2.IMREAD_GRAYSCALE | cv2.IMREAD_IGNORE_ORIENTATION
    for name in names:
        image = cv2.imread(str(image_path / name), flags)
        if image is not None:
            return image.shape[1], image.shape[0]
    raise InputError(image_path, "no readable image to take the camera size from")


def _from_camera_path(path: Path) -> tuple[dict[int, Camera], dict[str, int]]:
    """Cameras and (when listed) the camera id of each image name."""
    if path.is_file() and path.read_bytes()[:16] == b"SQLite format 3\x00":
        from obliq_colmap.priors.database import read_cameras_table

        con = sqlite3.connect(f"file:{path}?mode=ro", uri=True)
        try:
            cameras = read_cameras_table(con, path)
            names = dict(con.execute("SELECT name, camera_id FROM images").fetchall())
        finally:
            con.close()
        return cameras, {n: int(c) for n, c in names.items()}
    import pycolmap

    try:
        if path.is_dir():
            rec = pycolmap.Reconstruction(str(path))
            cams, names = (
                rec.cameras,
                {im.name: im.camera_id for im in rec.images.values()},
            )
        else:
            cams = _read_cameras_file(path)
            names = {}
    except (RuntimeError, ValueError) as exc:
        raise InputError(path, f"cannot read the cameras: {exc}") from None
    cameras = {}
    for cid, cam in cams.items():
        if cam.model.name not in SUPPORTED_MODELS:
            raise InputError(
                path, f"camera {cid} has non-perspective model {cam.model.name}"
            )
        cameras[int(cid)] = Camera.from_pycolmap(cam)
    return cameras, {n: int(c) for n, c in names.items()}


def _read_cameras_file(path: Path) -> dict:
    """The cameras of a lone ``cameras.txt``/``cameras.bin``.

    pycolmap reads whole models, so the file joins an empty model.
    """
    import tempfile

    import pycolmap

    with tempfile.TemporaryDirectory() as tmp:
        empty = pycolmap.Reconstruction()
        if path.suffix == ".txt":
            empty.write_text(tmp)
        else:
            empty.write_binary(tmp)
        (Path(tmp) / f"cameras{path.suffix}").write_bytes(path.read_bytes())
        return dict(pycolmap.Reconstruction(tmp).cameras)


def camera_source(
    options: PriorsOptions,
    names: list[str],
    image_path: Path | None,
    source: Path,
    fallback: dict[int, Camera] | None = None,
) -> tuple[dict[int, Camera], list[int]]:
    """Cameras and each image's camera id for a format without intrinsics.

    ``fallback`` (a database's own cameras) is used when no option is given.
    """
    if options.camera_path is not None:
        cameras, by_name = _from_camera_path(Path(options.camera_path))
    elif options.camera_params is not None:
        width, height = _image_size(image_path, names)
        cameras, by_name = (
            {1: parse_camera_params(options.camera_params, width, height)},
            {},
        )
    elif fallback:
        return fallback, []
    else:
        raise InputError(
            source,
            "this prior format carries no intrinsics: give --camera_path (a COLMAP "
            "model, cameras.txt/.bin or database) or --camera_params",
        )
    if by_name:
        missing = [n for n in names if n not in by_name]
        if missing:
            raise InputError(
                options.camera_path,
                f"{len(missing)} image(s) of {source} are not listed: {missing[:5]}",
            )
        return cameras, [by_name[n] for n in names]
    if len(cameras) != 1:
        raise InputError(
            options.camera_path,
            f"{len(cameras)} cameras and no images to tell which image uses which; "
            "give a model or database that lists the images",
        )
    (cid,) = cameras
    return cameras, [cid] * len(names)
