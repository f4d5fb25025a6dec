"""Options of the dense-matching export."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class DenseOptions:
    """Options of :func:`obliq_colmap.dense.export_dense`.

    Defaults follow COLMAP's ``image_undistorter`` and ``patch_match_stereo``
    where they have one.
    """

    #: longest side of the undistorted images, px (-1: full size), as
    #: ``image_undistorter --max_image_size``.
    max_image_size: int = -1
    #: an image needs at least this many points in front of it for its
    #: depth range. COLMAP takes the 1st and 99th percentile of its points'
    #: depths; from a handful of points on one building that range need not
    #: span the terrain and roofs of the whole frame.
    min_num_points: int = 20
    #: points of the workspace's model need at least this many observations
    #: (2 keeps every point, as COLMAP's image_undistorter). A point seen in
    #: two images is unchecked: a wrong match triangulates with no error,
    #: possibly far below the ground, and stretches the depth range of the
    #: images that see it (COLMAP's 1st-99th percentile tolerates 1 % of
    #: them); a third view checks it.
    min_track_length: int = 3
    #: source images per reference image (``__auto__, N`` in patch-match.cfg).
    num_src_images: int = 20
    #: ``--PatchMatchStereo.min_triangulation_angle`` (deg), COLMAP's default:
    #: a source image must see the shared points under at least this angle.
    min_triangulation_angle_deg: float = 1.0

    def __post_init__(self) -> None:
        if self.max_image_size == 0 or self.max_image_size < -1:
            raise ValueError("max_image_size must be positive or -1 (full size)")
        if self.min_num_points < 1:
            raise ValueError("min_num_points must be at least 1")
        if self.min_track_length < 2:
            raise ValueError("min_track_length must be at least 2")
        if self.num_src_images < 1:
            raise ValueError("num_src_images must be at least 1")
        if not 0.0 <= self.min_triangulation_angle_deg < 90.0:
            raise ValueError("min_triangulation_angle_deg must be in [0, 90)")
