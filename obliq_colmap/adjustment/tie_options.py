"""Options of the tie points (:func:`obliq_colmap.adjustment.tie_points`)."""

from __future__ import annotations

from dataclasses import dataclass

__all__ = ["TiePointOptions"]


@dataclass(kw_only=True)
class TiePointOptions:
    """Options of the tie points (COLMAP-like names)."""

    #: Images are down-sampled to this size for extraction (the bundle needs a
    #: few hundred good points per image, not the full resolution's thousands).
    max_image_size: int = 1000
    #: SIFT's cap before orientations (each keypoint may get two). Over the
    #: cap SIFT drops the finest scales first, the best located: at 1000 px
    #: 2000 keeps nearly all of octave 0 (urban-101, true poses: 24 % more
    #: tie points than 1200, their error at the truth 0.33 px against 0.35).
    max_num_features: int = 2000
    #: SIFT's first octave (COLMAP's ``SiftExtraction.first_octave``, there
    #: -1: the image up-sampled 2x first). Under the cap the up-sampled
    #: octave's keypoints were the ones dropped, so at 1000 px 0 finds as
    #: many of the same scales in a third to a fifth of the time
    #: (docs/journal/stage3-bundle.md).
    first_octave: int = 0
    #: A pair is matched when the overlap of its ground footprints is at
    #: least this share of the smaller footprint.
    min_overlap: float = 0.2
    #: Each image is matched with at most this many partners (largest overlap).
    max_pairs_per_image: int = 8
    #: Half of them are its best partners of a similar view (optical axes
    #: within this angle): a nadir image lies inside the larger oblique
    #: footprints, which would take all its places by overlap although
    #: SIFT matches across 45 deg poorly (our paper scene with a nadir head:
    #: 15-17 verified matches to an oblique neighbour, 32-36 to a nadir one).
    similar_view_deg: float = 30.0
    #: Pairs whose optical axes differ more are not matched. Two neighbouring
    #: heads (90 deg apart) are matched: on the external houses-102 scene
    #: (realistic ground texture) 1,930 of 6,124 verified points link two
    #: heads, all within 2 m of the true terrain; on our generator's
    #: synthetic texture none survive. Opposite heads see different sides.
    max_view_angle_deg: float = 100.0
    #: Match within the epipolar band of the given poses (pixels of the
    #: down-sampled image), else plain matching and pycolmap's two-view
    #: verification. Off: the bundle's tie points are matched before it
    #: from the per-image poses, which may be degrees off, and matches chosen
    #: by a wrong geometry would confirm it. SIFT's ratio test (COLMAP's
    #: max_ratio).
    guided_matching: bool = False
    max_epipolar_error_px: float = 2.0
    max_ratio: float = 0.9
    #: RANSAC of the two-view verification: at most this many trials (COLMAP's
    #: 10,000 cost 0.17 s a pair on urban-101 for 5 % more inliers than
    #: 2,000 at 0.04 s) and a fixed seed, so that a run repeats exactly.
    max_num_trials: int = 2000
    random_seed: int = 0
    #: Triangulated points whose reprojection error exceeds this are dropped.
    max_reproj_error_px: float = 3.0
    min_track_length: int = 2
    #: A tie point must lie in the scene the cameras look at: not deeper
    #: below the block's ground than this fraction of the flying height, not
    #: above the lowest camera, and within this many flying heights of a
    #: camera horizontally. A wrong match along the epipolar line of a guided
    #: pair reprojects well in both images wherever it lands (on the sample,
    #: 207 of 1,752 two-view points lay more than 1 km away, some tens of km
    #: below the ground; they stretched COLMAP's MVS depth ranges 35-47x).
    max_below_ground_fraction: float = 0.2
    max_distance_heights: float = 5.0
    num_threads: int = 2
    #: Processes of the SIFT extraction (1: in this process).
    num_workers: int = 2

    def __post_init__(self) -> None:
        if self.max_image_size < 64 or self.max_num_features < 8:
            raise ValueError("max_image_size must be >= 64 and max_num_features >= 8")
        if not 0.0 < self.min_overlap <= 1.0:
            raise ValueError("min_overlap must be in (0, 1]")
