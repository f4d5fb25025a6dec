"""The run's shared state: what the per-image stages made of each image, the
checked inputs, and the block as it stands.

Stage 3 (:mod:`obliq_colmap.adjustment`) and the pipeline
(:mod:`obliq_colmap.pipeline`) both read and write these, so they live here
and neither stage imports the pipeline. This module depends only on the
result types of the stages below it (registration, cadastre, bundle,
colmap_io, lines, geometry); none of those import it.

* :class:`ImageOutcome`: one image after stages 1-2 (and the verdicts).
* :class:`Inputs`: the checked inputs of a run, local frame of the map.
* :class:`BlockState`: poses, intrinsics and ground planes of the registered
  images, per image after stage 2, shared per head after the bundle.
* :func:`json_float`: a number of ``report.json`` (NaN and inf -> null).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from obliq_colmap.bundle import BundleResult
from obliq_colmap.cadastre import Cadastre, CadastreOptions
from obliq_colmap.colmap_io import Block
from obliq_colmap.geometry import Camera, Pose
from obliq_colmap.lines import Segments
from obliq_colmap.registration import RegistrationResult

__all__ = ["BlockState", "ImageOutcome", "Inputs", "json_float"]


def json_float(x: float | None) -> float | None:
    """``x`` as a number of a JSON report (``report.json``): a float, or None
    (null) when missing, NaN or infinite (JSON has no NaN)."""
    return float(x) if x is not None and math.isfinite(x) else None


@dataclass
class ImageOutcome:
    """What the per-image stages made of one image.

    Attributes
    ----------
    image_id, name : as in the priors.
    status : "registered", "failed" (no registration) or "unreadable".
    message : why, in words ("" when registered without remark).
    vp_status : the vanishing stage's status ("ok", "low_confidence", "no_vp").
    vertical_direction : (3,) array or None, detected, camera frame, down.
    vp, vp_covariance : (3,) and (3, 3) arrays or None: stage 1's vertical
        VP (homogeneous, unit, UNDISTORTED pixels of the priors' camera, the
        frame stage 1 measured it in) and its covariance; only where the
        vanishing stage's status is "ok" (the bundle observes them).
    segments : (N, 2, 2) array, the VP-constrained vertical segments in
        UNDISTORTED pixels (the registration's input).
    segments_free : (N, 2, 2) array or None, the same segments each fitted
        on its own edge points (its own direction, not stage 1's VP's), for
        the bundle's vertical rows; None: ``segments`` are.
    line_segments : Segments, all first-pass segments (undistorted pixels,
        with their bright side), the input of the facade-edge search.
    registration : RegistrationResult or None (unreadable image).
    camera : Camera or None, the intrinsics the registered pose belongs to
        (the priors' camera with the focal length refined for this image).
    rescued : the result comes from the second try with the block's ground.
    reregistered : the result comes from the try against the solved block
        (:func:`obliq_colmap.pipeline.reregister_failed`), after the first
        bundle.
    placed_by_ties : that try started from the pose its tie points give in
        the solved block (:mod:`obliq_colmap.pipeline.resection`).
    time_s : wall time per step, seconds.
    """

    image_id: int
    name: str
    status: str
    message: str = ""
    vp_status: str = ""
    vertical_direction: np.ndarray | None = None
    vp: np.ndarray | None = None
    vp_covariance: np.ndarray | None = None
    segments: np.ndarray = field(default_factory=lambda: np.zeros((0, 2, 2)))
    segments_free: np.ndarray | None = None
    line_segments: Segments = field(default_factory=Segments)
    registration: RegistrationResult | None = None
    camera: Camera | None = None
    rescued: bool = False
    reregistered: bool = False
    placed_by_ties: bool = False
    time_s: dict[str, float] = field(default_factory=dict)

    @property
    def registered(self) -> bool:
        return self.status == "registered"


@dataclass
class Inputs:
    """The checked inputs of a run, in the local frame of the cadastre."""

    image_path: Path
    cadastre_path: Path
    cadastre: Cadastre
    priors: Block  # local frame
    cameras: dict[int, Camera]  # in the result's camera model
    priors_path: Path | None = None  # the priors model, for messages
    #: the map options the run read the map with (its area among them): the
    #: workers read the same map with them
    cadastre_options: CadastreOptions | None = None
    #: the priors give positions only (their rotations are placeholders)
    position_only: bool = False


@dataclass
class BlockState:
    """Poses, intrinsics and ground planes of the registered images.

    Attributes
    ----------
    poses : dict image_id -> Pose, ``cam_from_world``, local frame.
    cameras : dict image_id -> Camera, the intrinsics each pose belongs to
        (per image after stage 2, which refines the focal length per image;
        the shared camera of the image's head after the bundle).
    planes : dict image_id -> (3,) ground plane ``z = a x + b y + c``.
    shared : bool, the cameras are shared per camera_id (after the bundle).
    solved : the images whose pose comes from a bundle (in the block's
        datum); the others are per-image registrations, each in its own.
    """

    poses: dict[int, Pose]
    cameras: dict[int, Camera]
    planes: dict[int, np.ndarray]
    shared: bool = False
    solved: frozenset[int] = frozenset()

    @classmethod
    def from_outcomes(cls, registered: Sequence[ImageOutcome]) -> BlockState:
        return cls(
            poses={o.image_id: o.registration.cam_from_world for o in registered},
            cameras={o.image_id: o.camera for o in registered},
            planes={o.image_id: o.registration.height_plane.copy() for o in registered},
        )

    def without(self, image_ids: Iterable[int]) -> BlockState:
        """The block without the images ``image_ids``."""
        keep = set(self.poses) - set(image_ids)
        return BlockState(
            poses={i: p for i, p in self.poses.items() if i in keep},
            cameras={i: c for i, c in self.cameras.items() if i in keep},
            planes={i: p for i, p in self.planes.items() if i in keep},
            shared=self.shared,
            solved=self.solved & keep,
        )

    def ground(self, image_id: int) -> Callable[[np.ndarray], np.ndarray]:
        """The image's ground plane as a function of (N, 2) local xy."""
        p = self.planes[image_id]
        return lambda xy: xy @ p[:2] + p[2]

    def ground_height(self, image_ids: Sequence[int] | None = None) -> float:
        """Median over the images (default all) of their ground plane's
        height under their camera (m)."""
        ids = list(self.poses) if image_ids is None else image_ids
        return float(
            np.median([self.ground(i)(self.poses[i].center[None, :2])[0] for i in ids])
        )

    def with_datum_correction(self, correction: dict[int, float]) -> BlockState:
        """Cameras and planes lowered by each image's height datum error (m).

        The errors are relative (the facade matches give height offsets
        between images); where some images are already solved, they are
        measured from the solved images' median and only the others move."""
        if self.solved:
            ref = [e for i, e in correction.items() if i in self.solved]
            ref = [e for e in ref if math.isfinite(e)]
            offset = float(np.median(ref)) if ref else 0.0
            correction = {
                i: e - offset for i, e in correction.items() if i not in self.solved
            }
        poses, planes = dict(self.poses), {k: v.copy() for k, v in self.planes.items()}
        for i, e in correction.items():
            if not math.isfinite(e):
                continue
            pose = poses[i]
            poses[i] = Pose.from_center(pose.rotation, pose.center - np.r_[0, 0, e])
            planes[i][2] -= e
        return dataclasses.replace(self, poses=poses, planes=planes)

    def with_bundle(
        self, result: BundleResult, image_camera: dict[int, int]
    ) -> BlockState:
        """The bundle's poses and shared cameras. The ground planes stay where
        they are (the datum correction put them in the block's datum; the
        ground does not move with a camera the bundle corrects: planes that
        followed the cameras' height changes put the facade bands and the
        next datum correction metres off, measured: a second bundle from the
        solved block then fell from 0.66 to 22 px on ``paper`` seed 1)."""
        cameras = {i: result.cameras[image_camera[i]] for i in result.poses}
        planes = {i: p.copy() for i, p in self.planes.items()}
        return BlockState(
            dict(result.poses), cameras, planes, True, frozenset(result.poses)
        )
