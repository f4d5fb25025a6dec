"""The stage-3 problem: facade edges and tracks over the block, and the
bundle problem (paper eq. 3) built from them and from stage 2's inliers.

* :func:`facade_stage`: horizontal facade edges of every registered image
  (:mod:`~obliq_colmap.adjustment.facades`) matched across images into
  tracks and per-image height datum corrections
  (:mod:`~obliq_colmap.adjustment.matching`), as a :class:`Stage3`.
* :func:`vertical_constraints`: each inlier corner-to-segment pair of stage 2
  as two fixed points on the corner's vertical.
* :func:`build_bundle_problem`: both as a
  :class:`~obliq_colmap.bundle.BundleProblem` (lines in raw pixels).
"""

from __future__ import annotations

import dataclasses
import logging
import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from obliq_colmap.adjustment.facades import FacadeEdges, facade_edges
from obliq_colmap.adjustment.matching import match_facade_edges
from obliq_colmap.adjustment.options import AdjustmentOptions
from obliq_colmap.adjustment.tie_options import TiePointOptions
from obliq_colmap.adjustment.ties import TiePoints, tie_rows
from obliq_colmap.adjustment.tracks import FacadeTracks
from obliq_colmap.bundle import BundleProblem
from obliq_colmap.bundle import residuals as res
from obliq_colmap.geometry import Camera, Pose, lines_through, vertical_vp_in_frame
from obliq_colmap.state import BlockState, ImageOutcome, Inputs, json_float

__all__ = [
    "Stage3",
    "build_bundle_problem",
    "facade_stage",
    "heights_on_vertical",
    "vertical_constraints",
]

logger = logging.getLogger(__name__)


@dataclass
class Stage3:
    """Facade edges of every registered image and their tracks.

    Attributes
    ----------
    ids : tuple of image ids, the order of ``facades`` and of the tracks'
        image indices.
    facades : list of FacadeEdges, per image.
    tracks : FacadeTracks.
    ends_raw : (H, 2, 2) array, each track observation's segment in raw
        pixels (set by :func:`build_bundle_problem`).
    row_obs : (R,) int array, per horizontal row of the bundle problem the
        track observation it holds (set by :func:`build_bundle_problem`).
    """

    ids: tuple[int, ...]
    facades: list[FacadeEdges]
    tracks: FacadeTracks
    ends_raw: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    row_obs: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    #: Per image id: RMS (px) of its final vertical and horizontal residuals.
    bundle_rms: dict[int, tuple[float, float]] = field(default_factory=dict)
    #: Per image id: the share of its constraints (map corners and facade
    #: observations) that the bundle's outlier rounds kept.
    constraints_kept: dict[int, float] = field(default_factory=dict)
    #: Per image id: the bundle's a-posteriori precision (px) of its
    #: constrained points (:attr:`BundleResult.image_precision_px`).
    bundle_precision: dict[int, float] = field(default_factory=dict)
    #: Per image id: how far along its verticals (px, signed, + up) the feet
    #: and the tops of its corners' vertical edges sit from where the other
    #: images put them, (2,) (:func:`edge_end_offsets`).
    end_offset_px: dict[int, np.ndarray] = field(default_factory=dict)
    #: Per image id: its tie observations in the last solve of points another
    #: head sees too, and the median reprojection error of all its tie
    #: observations (px), (count, median); absent without tie points.
    tie_fit: dict[int, tuple[int, float]] = field(default_factory=dict)
    #: Per image id whose vertical VP the rounds rejected against the block
    #: (:func:`~obliq_colmap.adjustment.rounds.vp_components`): the angle
    #: (deg) between the VP and the image's solved vertical at the rejection.
    vp_rejected: dict[int, float] = field(default_factory=dict)
    #: The last solve's problem (its tie rows go into the output with the
    #: solved points), None before a solve.
    bundle_problem: BundleProblem | None = None
    #: The track observations (indices into ``tracks``) that the last solve
    #: kept as rows, sorted; None before a solve.
    kept_observations: np.ndarray | None = None

    def report(self, outcomes: dict[int, ImageOutcome]) -> dict[str, Any]:
        t = self.tracks
        obs = np.bincount(t.image, minlength=len(self.ids))
        return {
            "num_tracks": t.num_tracks,
            "num_observations": t.num_observations,
            "num_image_pairs": len(t.pairs),
            "num_pair_matches": int(sum(p.num_matches for p in t.pairs)),
            "images": {
                outcomes[i].name: {
                    "facade_segments": len(f),
                    "walls": f.num_walls,
                    "observations": int(obs[k]),
                    "datum_correction_m": json_float(t.datum_correction[k]),
                    "bundle_rms_px": [
                        json_float(x) for x in self.bundle_rms.get(i, (math.nan,) * 2)
                    ],
                    "constraints_kept": json_float(
                        self.constraints_kept.get(i, math.nan)
                    ),
                    "bundle_precision_px": json_float(
                        self.bundle_precision.get(i, math.nan)
                    ),
                    "edge_end_offset_px": [
                        json_float(x)
                        for x in self.end_offset_px.get(i, (math.nan,) * 2)
                    ],
                }
                for k, (i, f) in enumerate(zip(self.ids, self.facades, strict=True))
            },
        }


def facade_stage(
    inputs: Inputs,
    state: BlockState,
    outcomes: dict[int, ImageOutcome],
    options: AdjustmentOptions,
) -> Stage3:
    """Horizontal facade edges per image, matched across images into tracks."""
    ids = tuple(sorted(state.poses))
    facades = []
    for i in ids:
        seg = outcomes[i].line_segments
        if near_nadir(state.cameras[i], state.poses[i]):
            # Walls are seen edge-on from above: a floor line and the eave
            # fall on one image line, so a facade edge fixes no height.
            seg = seg.subset(np.zeros(len(seg.endpoints), bool))
        prior = inputs.priors.cameras[inputs.priors.images[i].camera_id]
        facades.append(
            facade_edges(
                _in_camera(prior, state.cameras[i], seg.endpoints),
                seg.normal,
                state.cameras[i],
                state.poses[i],
                state.ground(i),
                inputs.cadastre,
                options.facades,
                seg.pixel_scale,
            )
        )
    grounds = np.array([state.planes[i] for i in ids]).reshape(-1, 3)
    tracks = match_facade_edges(facades, grounds, inputs.cadastre, options.matching)
    logger.info(
        "facade edges: %d segments on walls, %d tracks with %d observations",
        sum(len(f) for f in facades),
        tracks.num_tracks,
        tracks.num_observations,
    )
    return Stage3(ids, facades, tracks)


def near_nadir(camera: Camera, pose: Pose) -> bool:
    """Whether the image at ``pose`` is a nadir view (its vertical VP inside
    the frame), which stage 2 does not register to the map."""
    down = pose.rotation @ np.array([0.0, 0.0, -1.0])
    return vertical_vp_in_frame(camera, down) is not None


def _in_camera(prior: Camera, camera: Camera, segments: np.ndarray) -> np.ndarray:
    """(N, 2, 2) segments undistorted with the priors' camera (the frame of the
    per-image stages' segments) as undistorted pixels of ``camera``, whose
    distortion stage 2 may have refined (through the raw pixels)."""
    if not (prior.has_distortion or camera.has_distortion):
        return segments  # both frames are the raw pixels
    raw = prior.distort_pixels(segments.reshape(-1, 2))
    return camera.undistort_pixels(raw).reshape(segments.shape)


def raw_lines(camera: Camera, segments_undistorted: np.ndarray) -> np.ndarray:
    """(N, 3) unit lines through segments' endpoints in RAW (distorted) pixels."""
    ends = camera.distort_pixels(segments_undistorted.reshape(-1, 2)).reshape(-1, 2, 2)
    return lines_through(ends[:, 0], ends[:, 1])


def heights_on_vertical(
    camera: Camera, pose: Pose, xy: np.ndarray, raw: np.ndarray
) -> np.ndarray:
    """(N,) heights where the rays through RAW pixels (N, 2) of ``camera``
    (the intrinsics ``pose`` belongs to) pass closest to the verticals over
    map points xy (N, 2)."""
    rays = camera.cam_from_img(raw)
    d = np.column_stack([rays, np.ones(len(rays))]) @ pose.rotation  # world
    c = pose.center
    lam = np.sum(d[:, :2] * (xy - c[:2]), axis=1) / np.sum(d[:, :2] ** 2, axis=1)
    return c[2] + lam * d[:, 2]


def vertical_constraints(
    inputs: Inputs,
    outcomes: dict[int, ImageOutcome],
    state: BlockState,
    image_ids: Sequence[int],
    measured_directions: bool = False,
) -> dict[str, np.ndarray]:
    """Corner-to-vertical-line constraints from the registrations' inliers.

    Each inlier pair (map corner, vertical segment) gives TWO point-to-line
    residuals: the corner's vertical at the heights of the segment's two
    endpoints (fixed, from the start pose), projected, to the segment's line.
    Together they say that the segment lies on the image of the corner's
    vertical: its position AND its direction, i.e. the vanishing point,
    which is what holds the block's tilt (with one point per segment, or a
    free corner height, a tilted block fits the lines nearly as well:
    measured on the sample, 3 deg drift from the truth). The heights only
    place the points near the segment; sliding along the vertical does not
    change a distance to a line through the vanishing point.

    With ``measured_directions`` each segment's line is its own fit on its
    edge points (:attr:`ImageOutcome.segments_free`), not the line through
    stage 1's VP that stage 2 matched (a VP degrees off, as on detached
    houses, turns every segment of its image alike; a ~25 px segment's own
    direction is noisier).

    Returns
    -------
    dict with ``xy`` (M, 2) corner positions, ``height`` (M,), ``image`` (M,)
    index into ``image_ids``, ``line`` (M, 3) raw pixels, ``corner`` (M,)
    cadastre corner ids.
    """
    cad = inputs.cadastre
    parts: dict[str, list[np.ndarray]] = {
        k: [] for k in ("xy", "height", "image", "line", "corner")
    }
    for k, image_id in enumerate(image_ids):
        r = outcomes[image_id].registration
        if r is None or not r.success or len(r.inlier_pairs) == 0:
            continue
        prior_cam = inputs.priors.cameras[inputs.priors.images[image_id].camera_id]
        c = r.inlier_pairs[:, 0]
        ends = r.inlier_segments_px  # (K, 2, 2) undistorted
        if measured_directions and outcomes[image_id].segments_free is not None:
            ends = outcomes[image_id].segments_free[r.inlier_pairs[:, 1]]
        xy = np.repeat(cad.corner_xy[c], 2, axis=0)
        # Through the camera the pose belongs to (stage 2 refines focal and
        # lens): with the priors' camera the points land metres off along
        # the vertical, and under a lens that vertical's image is curved,
        # so they would leave the segment's chord (hard seed 1: the real
        # vertical lines alone left 1.8 px, scripts/diagnose/bundle_limit.py).
        camera = state.cameras.get(image_id) or prior_cam
        h = heights_on_vertical(
            camera,
            state.poses[image_id],
            xy,
            prior_cam.distort_pixels(ends.reshape(-1, 2)),
        )
        parts["xy"].append(xy)
        parts["height"].append(h)
        parts["image"].append(np.full(len(xy), k))
        parts["line"].append(np.repeat(raw_lines(prior_cam, ends), 2, axis=0))
        parts["corner"].append(np.repeat(c, 2))
    if not parts["xy"]:
        return dict(
            xy=np.zeros((0, 2)),
            height=np.zeros(0),
            image=np.zeros(0, np.int64),
            line=np.zeros((0, 3)),
            corner=np.zeros(0, np.int64),
        )
    return {k: np.concatenate(v) for k, v in parts.items()}


def _group_cameras(
    inputs: Inputs, state: BlockState, outcomes: dict[int, ImageOutcome]
) -> dict[int, Camera]:
    """Start intrinsics per camera_id: the result model's camera with the
    median of its images' per-image focal lengths (stage 2 refines the focal
    per image; the images of one head share one), and the median of the
    distortion of those images whose stage 2 refined it (one lens per head:
    a much better start than the priors' for the bundle). After a bundle
    (``state.shared``) the heads' solved cameras, as they stand."""
    if state.shared:
        return {
            inputs.priors.images[i].camera_id: dataclasses.replace(
                cam, camera_id=inputs.priors.images[i].camera_id
            )
            for i, cam in state.cameras.items()
        }
    ratios: dict[int, list[float]] = {}
    lenses: dict[int, list[np.ndarray]] = {}
    for i, cam in state.cameras.items():
        cid = inputs.priors.images[i].camera_id
        prior = inputs.priors.cameras[cid]
        ratios.setdefault(cid, []).append(cam.params[0] / prior.params[0])
        r = outcomes[i].registration
        if r is not None and r.distortion_refined:
            extra = res.focal_principal_extra_indices(cam.model)[2]
            lenses.setdefault(cid, []).append(cam.params[extra])
    out = {}
    for cid, r in ratios.items():
        cam = inputs.cameras[cid]
        focal, _, extra = res.focal_principal_extra_indices(cam.model)
        params = cam.params.copy()
        params[focal] *= float(np.median(r))
        if cid in lenses and len(lenses[cid][0]) == len(extra):
            params[extra] = np.median(np.array(lenses[cid]), axis=0)
        out[cid] = Camera(cam.model, cam.width, cam.height, params, cid)
    return out


def build_bundle_problem(
    inputs: Inputs,
    outcomes: dict[int, ImageOutcome],
    state: BlockState,
    stage3: Stage3,
    ties: TiePoints | None = None,
    tie_options: TiePointOptions | None = None,
    measured_directions: bool = False,
    map_vertex_sigma_m: float = 0.15,
    level_height_m: float = 2.0,
) -> BundleProblem:
    """The global bundle over the registered images (paper eq. 3).

    Vertical constraints: the registrations' inlier corner-to-segment pairs;
    horizontal ones: every observation of every facade track, anchored at
    the track's point on its map edge. Lines in RAW pixels (the bundle
    projects through the full camera model). The corner points are fixed
    (``BundleOptions.corner_heights = "fixed"``, see
    :func:`vertical_constraints`). Tie points (``ties``, matched across the
    block): triangulated from the block as it stands, rows of the bundle
    (:func:`~obliq_colmap.adjustment.ties.tie_rows`). Sets
    ``stage3.ends_raw`` and ``stage3.row_obs``. For the facade lines
    (``BundleOptions.facade_lines``): each observation's segment, each
    track's map edge direction and the prior sd of the line's angle about
    it, ``sqrt(2) map_vertex_sigma_m`` over the edge's length (two vertices'
    noise across the edge); the tracks at least ``level_height_m`` above the
    ground at the nearest observed map corner are level lines.
    """
    ids = stage3.ids
    v = vertical_constraints(inputs, outcomes, state, ids, measured_directions)
    t = stage3.tracks
    ends = np.zeros((t.num_observations, 2, 2))
    for k, i in enumerate(ids):
        sel = np.flatnonzero(t.image == k)
        if len(sel) == 0:
            continue
        # The facade edges are in the frame of the image's own camera
        # (facade_stage).
        und = stage3.facades[k].endpoints[t.row[sel]]
        ends[sel] = (
            state.cameras[i].distort_pixels(und.reshape(-1, 2)).reshape(-1, 2, 2)
        )
    stage3.ends_raw = ends
    lines = lines_through(ends[:, 0], ends[:, 1])
    stage3.row_obs = np.arange(t.num_observations)
    cameras = _group_cameras(inputs, state, outcomes)
    # Stage 1's vertical VPs where its status is "ok" (ImageOutcome.vp),
    # observations where BundleOptions.vp_observations.
    # Not in a nadir view: its VP lies among the short radial verticals near
    # the image centre, 4-10 deg off (our paper scene with a nadir head).
    with_vp = [
        i
        for i in ids
        if outcomes[i].vp is not None
        and not near_nadir(state.cameras[i], state.poses[i])
    ]
    tie = {}
    if ties is not None and len(ties.obs_point):
        xyz, img, point, xy, sd = tie_rows(
            ties,
            ids,
            [state.cameras[i].to_pycolmap() for i in ids],
            [state.poses[i].to_rigid3d() for i in ids],
            state.ground_height(ids),
            tie_options or TiePointOptions(),
        )
        tie = dict(tie_xyz=xyz, tie_image=img, tie_point=point, tie_xy=xy, tie_sd=sd)
    return BundleProblem(
        cameras=cameras,
        poses={i: state.poses[i] for i in ids},
        image_camera={i: inputs.priors.images[i].camera_id for i in ids},
        image_ids=ids,
        corner_xy=v["xy"],
        corner_heights=v["height"],
        vertical_image=v["image"],
        vertical_corner=np.arange(len(v["xy"])),
        vertical_line=v["line"],
        facade_heights=t.height,
        horizontal_image=t.image,
        horizontal_height=t.track,
        horizontal_anchor_xy=t.anchor_xy[t.track],
        horizontal_line=lines,
        horizontal_ends=ends,
        facade_direction=_edge_direction(inputs.cadastre.edge_normal[t.edge]),
        facade_angle_sigma=np.arctan2(
            np.sqrt(2.0) * map_vertex_sigma_m, inputs.cadastre.edge_length[t.edge]
        ),
        facade_level=_level_tracks(t, v["xy"], v["height"], level_height_m),
        # The INS attitude and the GNSS centres, observations where the
        # bundle is given their sigmas (BundleOptions.rotation_prior_sigma_deg,
        # position_prior_sigma_m).
        prior_rotations={
            i: inputs.priors.images[i].cam_from_world.rotation for i in ids
        },
        prior_centers={i: inputs.priors.images[i].cam_from_world.center for i in ids},
        # The priors' principal points (BundleOptions.principal_point_prior_sigma).
        prior_principal_points={
            c: inputs.priors.cameras[c].K[:2, 2].copy() for c in cameras
        },
        vertical_vps={i: outcomes[i].vp for i in with_vp},
        vertical_vp_covariances={i: outcomes[i].vp_covariance for i in with_vp},
        **tie,
    )


def _edge_direction(normal: np.ndarray) -> np.ndarray:
    """(J, 2) map edge directions ``u`` of (J, 2) outward normals ``n``, such
    that ``n = (u_y, -u_x)`` (a facade line's positive offset is outward)."""
    return np.column_stack([-normal[:, 1], normal[:, 0]])


def _level_tracks(
    tracks, corner_xy: np.ndarray, corner_height: np.ndarray, min_height_m: float
) -> np.ndarray:
    """(J,) whether each track lies ``min_height_m`` or more above the ground
    (the height of the observed map corner nearest its anchor): floors and
    eaves are level, kerbs and the foot of a wall follow the terrain. All
    level where no corner is observed."""
    if len(corner_xy) == 0:
        return np.ones(tracks.num_tracks, bool)
    _, nearest = cKDTree(corner_xy).query(tracks.anchor_xy)
    return tracks.height - corner_height[nearest] >= min_height_m
