"""Options and results of placing a missing image from VPs."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

#: statuses of :class:`PlacedImage`
PLACEMENT_STATUSES = (
    "placed",
    "unreadable",
    "no_vertical_vp",
    "no_horizontal_vp",
    "no_matches",
    "no_consensus",
)


@dataclass(kw_only=True)
class RelativeVPOptions:
    """How a missing image is placed from VPs and a few matches."""

    # --- horizontal VPs (step 1) ---
    #: segments shorter than this are neither hypotheses nor support, px
    min_segment_length_px: float = 20.0
    #: a segment supports a VP when both its endpoints lie this close to the
    #: line through its midpoint and the VP, px (stage 1 uses 1 px; facade
    #: lines are shorter and noisier than building corners)
    inlier_threshold_px: float = 1.5
    #: segments this close (deg) to the vertical pencil or to the horizon
    #: line say nothing about a horizontal direction: left out
    exclude_near_deg: float = 3.0
    #: RANSAC hypotheses (one segment each), evaluated at once
    num_hypotheses: int = 1024
    #: a horizontal VP needs this many supporting segments
    min_horizontal_inliers: int = 12
    #: at most this many horizontal VPs per image, each at least
    #: ``min_separation_deg`` from the others
    max_horizontal_vps: int = 3
    min_separation_deg: float = 10.0
    # --- rotation (step 2) ---
    #: candidates farther than this from the reference rotation are dropped
    max_rotation_from_reference_deg: float = 60.0
    # --- matches and position (step 3) ---
    #: a neighbour's horizontal directions are refined by the same
    #: directions (within ``pool_tolerance_deg``) of up to this many
    #: registered images nearest in name order (0: the neighbour's alone);
    #: one image's VP heading scatters by 0.1-0.3 deg (Herz-Jesu, true poses)
    pool_images: int = 8
    pool_tolerance_deg: float = 1.0
    #: registered images matched against (nearest in name order first)
    max_neighbours: int = 4
    #: a neighbour's keypoint is its SfM observation within this distance, px
    #: (0 with pycolmap's own extraction of the same file)
    max_track_distance_px: float = 1.0
    #: RANSAC inlier threshold of the position, px
    ransac_threshold_px: float = 4.0
    #: hypotheses (pairs of correspondences) for the position, at most,
    #: scored on at most ``max_score_points`` of the correspondences (the
    #: (pairs x points x 3) array stays under 50 MB; the winner's inliers
    #: are counted on all)
    max_pairs: int = 2000
    max_score_points: int = 1000
    #: the position needs this many inlier correspondences, and this share
    #: of all (COLMAP's mapper: ``abs_pose_min_inlier_ratio`` 0.25): a wrong
    #: rotation candidate still gathers a few inliers among thousands
    min_inliers: int = 6
    min_inlier_ratio: float = 0.25
    seed: int = 0


@dataclass
class HorizontalVPs:
    """An image's horizontal VPs: (K, 3) unit directions in the camera frame
    (perpendicular to the vertical), (K,) supporting segment counts and
    (K, N) inlier masks over the segments given."""

    directions: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    num_inliers: np.ndarray = field(default_factory=lambda: np.zeros(0, int))
    inliers: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), bool))


@dataclass
class ImageVPs:
    """One image's VP triplet(s): ``down`` (3,) the world's down in the camera
    frame (None: no vertical VP) and its horizontal VPs."""

    status: str
    message: str
    down: np.ndarray | None = None
    horizontal: HorizontalVPs = field(default_factory=HorizontalVPs)


@dataclass
class PlacedImage:
    """One missing image's fate. ``cam_from_world`` (3, 4) in the model frame
    when placed; ``points2D`` (M, 2) COLMAP pixels of its inlier keypoints and
    ``point3D_ids`` (M,) the model points they observe."""

    name: str
    status: str
    message: str
    cam_from_world: np.ndarray | None = None
    neighbour: str | None = None
    camera_id: int = -1
    num_matches: int = 0
    num_inliers: int = 0
    num_candidates: int = 0
    points2D: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    point3D_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))

    def report(self) -> dict:
        return {
            "status": self.status,
            "message": self.message,
            "neighbour": self.neighbour,
            "num_matches": self.num_matches,
            "num_inliers": self.num_inliers,
            "num_rotation_candidates": self.num_candidates,
        }
