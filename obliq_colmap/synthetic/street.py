"""A walk along a street of the synthetic city: a phone's images and control points.

The terrestrial counterpart of the oblique flight (issue 27): one hand-held
camera ``street_camera_height_m`` above the terrain, stepping
``street_step_m`` along the sidewalk of the street nearest the city centre
and looking across it at the opposite facades (``street_forward_deg``
forward of their normal, ``street_pitch_deg`` up). Everything is in the
LOCAL frame of the city, as in :mod:`obliq_colmap.synthetic.cameras`.

Control points are building corners of mapped buildings (at ground level
and at the eaves, i.e. on the facades) seen in several images, about
``street_gcp_spacing_m`` apart along the street; they are written as an
OpenSfM ``gcp_list.txt`` (:func:`write_gcp_list`).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from obliq_colmap.colmap_io import Block, ImageRecord
from obliq_colmap.control.model import ControlObservation, ControlPoint, ControlPoints
from obliq_colmap.geometry import Pose, project
from obliq_colmap.synthetic.cameras import (
    STREAM_FLIGHT,
    rotation_from_angles,
    stream,
    true_cameras,
)
from obliq_colmap.synthetic.city import SIDEWALK_M, City
from obliq_colmap.synthetic.options import SceneOptions

#: fewest images a control point must be seen in to be chosen.
MIN_GCP_VIEWS = 3
#: height above the ground of the facade points of building corners (a
#: surveyor's reflectorless shot above the parked cars), m.
FACADE_POINT_HEIGHT_M = 3.0


@dataclass(frozen=True)
class StreetWalk:
    """The street walked (local frame).

    Attributes
    ----------
    start : (2,) first nominal camera position (plan), m.
    direction : (2,) unit walking direction.
    facade_normal : (2,) unit horizontal direction from the cameras towards
        the facades they look at.
    street_width_m : property line to property line, m.
    """

    start: np.ndarray
    direction: np.ndarray
    facade_normal: np.ndarray
    street_width_m: float


def choose_street(city: City) -> StreetWalk:
    """The sidewalk walk along the street whose centre line passes nearest the origin.

    The camera walks on the sidewalk of the +side and looks at the facades of
    the -side, so the facades are about a street width minus half a
    sidewalk away.
    """
    o = city.options
    L = city.layout
    lines = [(0, c, w) for c, w in zip(L.xs, L.wx, strict=True)]
    lines += [(1, c, w) for c, w in zip(L.ys, L.wy, strict=True)]
    axis, c0, width = min(lines, key=lambda t: abs(t[1]))
    offset = c0 + (width / 2.0 - SIDEWALK_M / 2.0)
    length = (o.street_num_images - 1) * o.street_step_m
    if axis == 0:  # street along grid y at x = c0
        start_g, dir_g, normal_g = [offset, -length / 2.0], [0.0, 1.0], [-1.0, 0.0]
    else:
        start_g, dir_g, normal_g = [-length / 2.0, offset], [1.0, 0.0], [0.0, -1.0]
    return StreetWalk(
        start=L.to_local(np.array(start_g)),
        direction=L.to_local(np.array(dir_g)),
        facade_normal=L.to_local(np.array(normal_g)),
        street_width_m=float(width),
    )


def street_block(city: City, options: SceneOptions, seed: int) -> Block:
    """True camera and poses (local frame) of the walk, with hand-held jitter.

    One camera (camera_id 1, the model of ``options.distortion``) for all
    images ``street_NNN.jpg``, in walking order.
    """
    walk = choose_street(city)
    rng = stream(seed, STREAM_FLIGHT, 3)
    camera = true_cameras(options, seed)[1]
    block = Block(cameras={1: camera})
    fwd = np.radians(options.street_forward_deg)
    view = np.cos(fwd) * walk.facade_normal + np.sin(fwd) * walk.direction
    heading = np.degrees(np.arctan2(view[0], view[1]))
    sj, sm = options.street_jitter_deg, options.street_jitter_m
    for k in range(options.street_num_images):
        xy = walk.start + k * options.street_step_m * walk.direction
        xy = xy + rng.normal(0.0, sm, 2)
        z = float(city.terrain.height(xy[0], xy[1])) + options.street_camera_height_m
        z += rng.normal(0.0, sm / 2.0)
        R = rotation_from_angles(
            heading + rng.normal(0.0, sj),
            90.0 + options.street_pitch_deg + rng.normal(0.0, sj),
            rng.normal(0.0, sj),
        )
        block.images[k + 1] = ImageRecord(
            k + 1, f"street_{k:03d}.jpg", 1, Pose.from_center(R, [*xy, z])
        )
    return block


def with_facade_points(city: City, corners: dict) -> dict:
    """``corners`` plus, for every ground corner, the point on the building's
    vertical corner edge :data:`FACADE_POINT_HEIGHT_M` above it (kind
    "facade"), for walls at least 1 m taller than that. Same keys as
    :func:`obliq_colmap.synthetic.city.corners`; the new points come last.
    """
    top = {b.id: b.base_z + b.height_m for b in city.buildings}
    kind = np.asarray(corners["kind"])
    z_top = np.array([top[b] for b in corners["building"]], float)
    sel = (kind == "ground") & (
        z_top - corners["xyz"][:, 2] >= FACADE_POINT_HEIGHT_M + 1.0
    )
    xyz = corners["xyz"][sel] + [0.0, 0.0, FACADE_POINT_HEIGHT_M]
    return {
        "xyz": np.concatenate([corners["xyz"], xyz]),
        "building": np.concatenate([corners["building"], corners["building"][sel]]),
        "kind": list(corners["kind"]) + ["facade"] * int(sel.sum()),
        "dir_a": np.concatenate([corners["dir_a"], corners["dir_a"][sel]]),
        "dir_b": np.concatenate([corners["dir_b"], corners["dir_b"][sel]]),
    }


def street_control_points(
    city: City,
    corners: dict,
    gt_local: Block,
    visible: dict[str, list[int]],
    spacing_m: float,
) -> ControlPoints:
    """Control points about ``spacing_m`` apart along the walk, true positions.

    Candidates are the ground, eave and facade corners of mapped buildings
    visible in at least :data:`MIN_GCP_VIEWS` images. Walking along the
    street, the next point is the best-seen candidate within 10 m past the
    previous one plus ``spacing_m``, alternately preferring ground and
    facade corners.

    Parameters
    ----------
    corners : :func:`with_facade_points` of ``city``'s corners (local).
    gt_local : the true walk (local frame).
    visible : image name -> indices into ``corners`` visible in it.

    Returns
    -------
    ControlPoints in ABSOLUTE coordinates of the scene's CRS, observations
    the exact projections (COLMAP pixels) in the images seeing each point.
    """
    xyz = corners["xyz"]
    n_views = np.zeros(len(xyz), int)
    for idx in visible.values():
        n_views[np.asarray(idx, int)] += 1
    in_map = {b.id: b.in_map for b in city.buildings}
    kind = np.asarray(corners["kind"])
    mapped = np.array([in_map[b] for b in corners["building"]], bool)
    cand = np.nonzero(
        mapped
        & (n_views >= MIN_GCP_VIEWS)
        & np.isin(kind, ("ground", "eave", "facade"))
    )[0]
    walk = choose_street(city)
    s = xyz[cand, :2] @ walk.direction
    chosen: list[int] = []
    target = -np.inf
    while True:
        ahead = cand[s >= target]
        if len(ahead) == 0:
            break
        s_ahead = s[s >= target]
        near = ahead[s_ahead < s_ahead.min() + 10.0]
        prefer = "ground" if len(chosen) % 2 == 0 else "facade"
        score = n_views[near] + 1000 * (kind[near] == prefer)
        best = int(near[np.argmax(score)])
        chosen.append(best)
        target = float(xyz[best, :2] @ walk.direction) + spacing_m
    points = []
    for k, i in enumerate(chosen):
        obs = []
        for im in gt_local.images.values():
            if i in set(visible.get(im.name, ())):
                cam = gt_local.cameras[im.camera_id]
                xy, _ = project(cam, im.cam_from_world, xyz[i][None])
                obs.append(ControlObservation(im.name, xy[0]))
        points.append(ControlPoint(f"gcp_{k:02d}_{kind[i]}", xyz[i] + city.origin, obs))
    return ControlPoints(points, city.options.crs)


def write_gcp_list(path: str | Path, control: ControlPoints) -> int:
    """Write ``control`` as an OpenSfM ``gcp_list.txt``; returns the lines written.

    First line the projection (``control.crs``, e.g. ``EPSG:25832``), then
    one line per observation: ``geo_x geo_y geo_z im_x im_y image_name
    gcp_name`` with pixels in OpenSfM's convention (the top-left pixel's
    centre at (0, 0): COLMAP's minus 0.5).
    """
    if not control.crs:
        raise ValueError("a gcp_list.txt needs a projection (control.crs)")
    lines = [control.crs]
    for p in control.points:
        for ob in p.observations:
            u, v = np.asarray(ob.xy, float) - 0.5
            lines.append(
                f"{p.xyz[0]:.4f} {p.xyz[1]:.4f} {p.xyz[2]:.4f} "
                f"{u:.3f} {v:.3f} {ob.image_name} {p.name}"
            )
    Path(path).write_text("\n".join(lines) + "\n")
    return len(lines) - 1


def read_gcp_list(path: str | Path) -> ControlPoints:
    """Read back a file of :func:`write_gcp_list` (its own projection and columns).

    Observations in COLMAP pixels; not a general reader of the format (the
    ``control`` package has that).
    """
    lines = [x.split() for x in Path(path).read_text().splitlines() if x.strip()]
    points: dict[str, ControlPoint] = {}
    for row in lines[1:]:
        name = row[6]
        if name not in points:
            points[name] = ControlPoint(name, np.array(row[:3], float))
        xy = np.array(row[3:5], float) + 0.5
        points[name].observations.append(ControlObservation(row[5], xy))
    return ControlPoints(list(points.values()), " ".join(lines[0]))
