"""Write and read a synthetic scene folder.

Layout of a scene folder (all coordinates ABSOLUTE, ``world_abs = local +
origin``; the local frame is only used internally for float precision)::

    images/NAME.jpg       rendered images (JPEG)
    cadastre.geojson      the map: Polygon / MultiPolygon footprints with
                          realistic discrepancies, properties {id, height?}
    priors/               COLMAP binary model, rough poses and intrinsics,
                          camera z in another vertical datum
    gt/                   COLMAP binary model, exact (same ids and names)
    gt_buildings.json     true 3D corners, building table, visible corners
    gcp_list.txt          street scenes: control points (OpenSfM format)
    scene.json            every parameter needed to rebuild the scene
"""

from __future__ import annotations

import json
import logging
import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
from shapely.geometry import MultiPolygon

from obliq_colmap.colmap_io import Block, read_model, to_reconstruction
from obliq_colmap.errors import InputError
from obliq_colmap.files import AtomicFolder
from obliq_colmap.geometry import Camera, Pose
from obliq_colmap.parallel import WorkerPool
from obliq_colmap.synthetic import city as C
from obliq_colmap.synthetic.cameras import (
    STREAM_CADASTRE,
    STREAM_RENDER,
    prior_block,
    stream,
    true_block,
)
from obliq_colmap.synthetic.options import SceneOptions
from obliq_colmap.synthetic.render import render_depth, render_image
from obliq_colmap.synthetic.street import (
    street_block,
    street_control_points,
    with_facade_points,
    write_gcp_list,
)
from obliq_colmap.synthetic.truth import (
    vertical_edge_segments,
    vertical_vp,
    visible_corners,
)

logger = logging.getLogger(__name__)

SCENE_FORMAT = "obliq-colmap synthetic scene"
SCENE_VERSION = 1


# --------------------------------------------------------------------------
# Cadastre and ground-truth files
# --------------------------------------------------------------------------


def cadastre_features(city: C.City, seed: int) -> list[dict]:
    """GeoJSON features of the mapped buildings (absolute coordinates).

    Discrepancies: buildings missing from the map and demolished ones
    (``Building.in_map`` / ``in_scene``), whole-building shifts
    (``shift_m``), and per-vertex noise of ``cadastre_vertex_noise_m`` that
    is the same for a vertex shared by two buildings (party walls).
    """
    o = city.options
    rng = stream(seed, STREAM_CADASTRE, 2)
    noise: dict[tuple[int, int], np.ndarray] = {}
    origin = city.origin[:2]

    def jitter(xy: np.ndarray) -> np.ndarray:
        out = np.empty_like(xy)
        for i, p in enumerate(xy):
            key = (int(round(p[0] * 1000)), int(round(p[1] * 1000)))
            if key not in noise:
                noise[key] = rng.normal(0.0, o.cadastre_vertex_noise_m, 2)
            out[i] = p + noise[key]
        return out

    features = []
    for b in city.buildings:
        if not b.in_map:
            continue
        polys = []
        for part in b.parts:
            rings = C._rings(part)
            coords = []
            for k, ring in enumerate(rings):
                xy = jitter(ring) + np.asarray(b.shift_m) + origin
                if (k == 0) != (_signed_area(xy) > 0):
                    xy = xy[
                        ::-1
                    ]  # exterior counter-clockwise, holes clockwise (RFC 7946)
                closed = np.vstack([xy, xy[:1]])
                coords.append(
                    [[round(float(x), 3), round(float(y), 3)] for x, y in closed]
                )
            polys.append(coords)
        if isinstance(b.footprint, MultiPolygon):
            geom = {"type": "MultiPolygon", "coordinates": polys}
        else:
            geom = {"type": "Polygon", "coordinates": polys[0]}
        props: dict = {"id": int(b.id)}
        if rng.uniform() < o.cadastre_height_fraction:
            props["height"] = round(float(b.height_m), 1)
        features.append({"type": "Feature", "properties": props, "geometry": geom})
    return features


def _signed_area(xy: np.ndarray) -> float:
    x, y = xy[:, 0], xy[:, 1]
    return 0.5 * float(np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y))


def write_cadastre(path: Path, city: C.City, seed: int) -> int:
    features = cadastre_features(city, seed)
    doc = {
        "type": "FeatureCollection",
        "crs": {"type": "name", "properties": {"name": city.options.crs}},
        "features": features,
    }
    path.write_text(json.dumps(doc, separators=(",", ":")) + "\n")
    return len(features)


def buildings_table(city: C.City) -> list[dict]:
    z0 = city.origin[2]
    return [
        {
            "id": int(b.id),
            "in_scene": bool(b.in_scene),
            "in_map": bool(b.in_map),
            "shift_m": [float(b.shift_m[0]), float(b.shift_m[1])],
            "height_m": float(b.height_m),
            "base_z": float(b.base_z + z0),
            "roof": b.roof,
            "ridge_height_m": float(b.ridge_height_m),
            "num_parts": len(b.parts),
        }
        for b in city.buildings
    ]


# --------------------------------------------------------------------------
# Rendering workers
# --------------------------------------------------------------------------

_WORKER: dict = {}


def _init_worker(city, corners, options, seed, image_dir) -> None:
    _WORKER.update(
        city=city, corners=corners, options=options, seed=seed, image_dir=image_dir
    )


def _render_task(task) -> tuple[str, list[int], dict]:
    image_id, name, camera, pose = task
    w = _WORKER
    rng = stream(w["seed"], STREAM_RENDER, image_id)
    image, depth, buffers = render_image(w["city"], camera, pose, w["options"], rng)
    path = Path(w["image_dir"]) / name
    ok = cv2.imwrite(
        str(path),
        image[..., ::-1],
        [cv2.IMWRITE_JPEG_QUALITY, int(w["options"].jpeg_quality)],
    )
    if not ok:
        raise OSError(f"cannot write {path}")
    vis = visible_corners(w["corners"], camera, pose, depth)
    return name, [int(i) for i in vis], buffers["timing_s"]


def generate_scene(
    output_path: str | Path,
    options: SceneOptions,
    *,
    seed: int,
    show_progress: bool = True,
    num_workers: int | None = None,
    preset: str | None = None,
) -> Path:
    """Generate a synthetic scene folder atomically (see the module docstring).

    Parameters
    ----------
    output_path : folder to create (must not exist or be empty).
    options : SceneOptions.
    seed : the scene seed; the same (options, seed) give the same scene.
    show_progress : tqdm bar over the rendered images.
    num_workers : rendering processes; None = os.cpu_count(), 1 = in-process.
    preset : name recorded in scene.json.

    Returns
    -------
    Path of the scene folder.

    Raises
    ------
    InputError
        The output folder exists and is not empty, or its parent is missing.
    """
    t_start = time.perf_counter()
    output_path = Path(output_path)
    folder = AtomicFolder(output_path)  # checks the output path before any work
    city = C.build_city(options, seed)
    if options.scene_kind == "street":
        gt_local = street_block(city, options, seed)
    else:
        gt_local = true_block(options, seed)
    priors_local = prior_block(options, seed, gt_local)
    corners = C.corners(city)
    origin = city.origin
    n_scene = sum(b.in_scene for b in city.buildings)
    logger.info(
        "city: %d buildings (%d in the scene), %d triangles, %d images of %dx%d",
        len(city.buildings),
        n_scene,
        len(city.faces),
        len(gt_local.images),
        options.image_width_px,
        options.image_height_px,
    )
    tasks = [
        (im.image_id, im.name, gt_local.cameras[im.camera_id], im.cam_from_world)
        for im in gt_local.images.values()
    ]
    workers = (os.cpu_count() or 1) if num_workers is None else max(1, int(num_workers))
    workers = min(workers, len(tasks))
    with folder as tmp:
        image_dir = tmp / "images"
        image_dir.mkdir()
        # a street's control points include facade points, tested with the rest
        street = options.scene_kind == "street"
        tested = with_facade_points(city, corners) if street else corners
        initargs = (city, tested, options, seed, str(image_dir))
        with WorkerPool(
            workers,
            _init_worker,
            initargs,
            progress=show_progress,
            unit="image",
        ) as pool:
            results = pool.map(_render_task, tasks, "render")
        for name in ("gt", "priors"):
            (tmp / name).mkdir()
        to_reconstruction(gt_local.shifted(-origin)).write_binary(str(tmp / "gt"))
        to_reconstruction(priors_local.shifted(-origin)).write_binary(
            str(tmp / "priors")
        )
        n_features = write_cadastre(tmp / "cadastre.geojson", city, seed)
        gt_doc = {
            "crs": options.crs,
            "corners": [
                [round(float(v), 4) for v in p] for p in corners["xyz"] + origin
            ],
            "corner_building": [int(b) for b in corners["building"]],
            "corner_kind": list(corners["kind"]),
            "buildings": buildings_table(city),
            "visible_corners": {
                name: [i for i in vis if i < len(corners["xyz"])]
                for name, vis, _ in results
            },
        }
        (tmp / "gt_buildings.json").write_text(json.dumps(gt_doc) + "\n")
        n_gcp = 0
        if street:
            control = street_control_points(
                city,
                tested,
                gt_local,
                {name: vis for name, vis, _ in results},
                options.street_gcp_spacing_m,
            )
            write_gcp_list(tmp / "gcp_list.txt", control)
            n_gcp = len(control)
        timings = np.array(
            [[t["raster"], t["shade"], t["post"]] for _, _, t in results]
        )
        scene_doc = {
            "format": SCENE_FORMAT,
            "version": SCENE_VERSION,
            "preset": preset,
            "seed": int(seed),
            "crs": options.crs,
            "origin": [float(v) for v in origin],
            "vertical_datum_offset_m": float(options.prior_vertical_datum_offset_m),
            "image_size": [options.image_width_px, options.image_height_px],
            "camera_model": options.camera_model,
            "images": [t[1] for t in tasks],
            "counts": {
                "buildings": len(city.buildings),
                "buildings_in_scene": int(n_scene),
                "map_features": int(n_features),
                "corners": len(corners["xyz"]),
                "triangles": len(city.faces),
                "control_points": n_gcp,
            },
            "render_median_s": dict(
                zip(
                    ("raster", "shade", "post"),
                    np.median(timings, 0).round(3).tolist(),
                    strict=True,
                )
            ),
            "options": options.to_json(),
        }
        (tmp / "scene.json").write_text(json.dumps(scene_doc, indent=2) + "\n")
    logger.info(
        "wrote %s: %d images, %d map features, %d corners in %.1f s",
        output_path,
        len(tasks),
        n_features,
        len(corners["xyz"]),
        time.perf_counter() - t_start,
    )
    return output_path


# --------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------


@dataclass
class SyntheticScene:
    """A scene folder read back, with its city rebuilt (not re-rendered).

    Attributes
    ----------
    path : scene folder. options, seed, preset : as generated.
    origin : (3,) absolute coordinates of the local origin.
    city : City (local frame). gt, priors : Blocks in ABSOLUTE coordinates.
    buildings : the parsed gt_buildings.json.
    """

    path: Path
    options: SceneOptions
    seed: int
    preset: str | None
    origin: np.ndarray
    crs: str
    city: C.City
    gt: Block
    priors: Block
    buildings: dict
    _gt_local: Block | None = field(default=None, repr=False)
    _depth: dict = field(default_factory=dict, repr=False)
    _edges: dict | None = field(default=None, repr=False)

    @property
    def gt_local(self) -> Block:
        """The true block in the LOCAL frame of the city."""
        if self._gt_local is None:
            self._gt_local = self.gt.shifted(self.origin)
        return self._gt_local

    def camera_pose(self, image_name: str) -> tuple[Camera, Pose]:
        """True camera and LOCAL cam_from_world of an image."""
        im = self.gt_local.image_by_name(image_name)
        return self.gt_local.cameras[im.camera_id], im.cam_from_world

    def image_path(self, image_name: str) -> Path:
        return self.path / "images" / image_name

    def depth(self, image_name: str) -> np.ndarray:
        """(H, W) z-buffer (camera z, m) of the true camera, cached."""
        if image_name not in self._depth:
            camera, pose = self.camera_pose(image_name)
            self._depth[image_name] = render_depth(self.city, camera, pose)[0]
        return self._depth[image_name]

    @property
    def vertical_edges(self) -> dict:
        if self._edges is None:
            self._edges = C.vertical_edges(self.city)
        return self._edges


def load_scene(path: str | Path) -> SyntheticScene:
    """Read a scene folder: scene.json, gt and priors models, gt_buildings.json.

    The city is rebuilt deterministically from the stored options and seed.

    Raises
    ------
    InputError
        Missing or invalid scene.json, missing models.
    """
    path = Path(path)
    scene_file = path / "scene.json"
    if not scene_file.is_file():
        raise InputError(path, "not a synthetic scene folder (no scene.json)")
    try:
        doc = json.loads(scene_file.read_text())
        if doc.get("format") != SCENE_FORMAT:
            raise ValueError(f"format is {doc.get('format')!r}")
        options = SceneOptions.from_json(doc["options"])
        seed = int(doc["seed"])
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(scene_file, f"invalid scene.json: {exc}") from None
    city = C.build_city(options, seed)
    origin = np.asarray(doc["origin"], float)
    if not np.allclose(origin, city.origin):
        raise InputError(scene_file, "origin does not match the options")
    buildings = json.loads((path / "gt_buildings.json").read_text())
    return SyntheticScene(
        path=path,
        options=options,
        seed=seed,
        preset=doc.get("preset"),
        origin=origin,
        crs=doc["crs"],
        city=city,
        gt=read_model(path / "gt"),
        priors=read_model(path / "priors"),
        buildings=buildings,
    )


def true_vertical_edges(
    scene: SyntheticScene, image_name: str, min_length_px: float = 4.0
) -> dict:
    """Visible parts of all true 3D vertical edges in one image.

    Parameters
    ----------
    scene : SyntheticScene.
    image_name : name of an image of the scene.
    min_length_px : shorter visible pieces are dropped.

    Returns
    -------
    dict with ``segments`` (M, 2, 2) float pixel end points in the image as
    rendered (distorted; COLMAP pixel convention), ``segments_undistorted``
    (M, 2, 2) the same in pixels of the pinhole part K, ``kind`` (M,) str
    array ("corner": building corners; "texture": window frames and shop
    fronts; "clutter": sheds, roof boxes, cars), ``edge_index`` (M,) and
    ``points3D`` (M, 2, 3) ABSOLUTE 3D end points.
    """
    camera, pose = scene.camera_pose(image_name)
    out = vertical_edge_segments(
        scene.vertical_edges,
        camera,
        pose,
        scene.depth(image_name),
        min_length_px=min_length_px,
    )
    out["points3D"] = out["points3D"] + scene.origin
    return out


def true_vertical_vp(scene: SyntheticScene, image_name: str) -> np.ndarray:
    """(3,) homogeneous vertical vanishing point of an image, unit norm.

    In UNDISTORTED pixel coordinates (the pinhole part ``K`` of the true
    camera; identical to image pixels for PINHOLE cameras).
    """
    camera, pose = scene.camera_pose(image_name)
    return vertical_vp(camera, pose)
