"""Options of the synthetic oblique city and its named presets.

One keyword-only dataclass holds every parameter of a scene; the presets are
instances of it and variants are made with :func:`dataclasses.replace`, never
by mutating a shared default. Every field is written to ``scene.json`` so
that the scene can be rebuilt exactly (with the seed).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

#: Image width (px) at which ``gsd_m`` and ``principal_point_offset_px`` hold.
REFERENCE_WIDTH_PX = 2004

#: Districts: the probability of each block type (the builder's ``_<kind>``
#: methods). "mixed" is the inner city every preset had before districts.
DISTRICT_BLOCKS: dict[str, dict[str, float]] = {
    "mixed": {
        "terrace": 0.34, "courtyard": 0.13, "houses": 0.25, "mixed": 0.21, "park": 0.07
    },
    "dense": {"terrace": 0.55, "courtyard": 0.3, "mixed": 0.15},
    "houses": {"houses": 0.92, "park": 0.08},
    "industrial": {"halls": 0.8, "mixed": 0.12, "park": 0.08},
    "highrise": {"towers": 0.55, "courtyard": 0.2, "mixed": 0.1, "park": 0.15},
}  # fmt: skip

#: Allowed values of ``SceneOptions.distortion`` and their COLMAP models.
DISTORTION_MODELS = {
    "none": "PINHOLE",
    "simple_radial": "SIMPLE_RADIAL",
    "radial": "RADIAL",
    "opencv": "OPENCV",
}

#: Kinds of scene: an oblique flight (the default) or a walk along a street
#: (:mod:`obliq_colmap.synthetic.street`).
SCENE_KINDS = ("oblique", "street")


@dataclass(kw_only=True, frozen=True)
class SceneOptions:
    """All parameters of a synthetic scene (units in the names or comments)."""

    #: "oblique" (the four-headed flight) or "street" (a walk, ``street_*``).
    scene_kind: str = "oblique"

    # --- flight and cameras -------------------------------------------------
    #: images per viewing direction along the look direction (rows) ...
    grid_rows: int = 3
    #: ... and across it (columns); four directions (N, E, S, W) in total.
    grid_cols: int = 3
    #: forward/side overlap of neighbouring footprints of one direction (0-1).
    overlap: float = 0.35
    #: nominal angle between the optical axis and the nadir, degrees.
    tilt_deg: float = 45.0
    #: a fifth, nadir camera (a five-camera oblique system): ``grid_rows x
    #: grid_cols`` images ``D_rc.jpg`` of camera 5, at the obliques' flying
    #: height over the block's centre, with the same overlap.
    nadir_head: bool = False
    #: horizontal field of view, degrees; kept when the image width changes.
    horizontal_fov_deg: float = 45.0
    #: ground sampling distance at the image centre (across the view, i.e.
    #: distance / focal) at the reference width of 2004 px, metres per pixel.
    gsd_m: float = 0.15
    #: image width in pixels; the height is ``round(width / image_aspect)``.
    image_width_px: int = 2004
    #: width / height.
    image_aspect: float = 1.5
    #: largest principal-point offset from the image centre, px at 2004 px.
    principal_point_offset_px: float = 8.0
    #: relative spread of the true focal length between heads (uniform, +-).
    focal_spread: float = 0.01
    #: flight irregularity (standard deviations): tilt, heading, roll in
    #: degrees, horizontal position per axis and altitude in metres.
    jitter_tilt_deg: float = 1.5
    jitter_heading_deg: float = 1.5
    jitter_roll_deg: float = 1.0
    jitter_position_m: float = 3.0
    jitter_altitude_m: float = 2.0
    #: lens distortion of the true cameras: "none" (COLMAP PINHOLE),
    #: "radial" (RADIAL: k1, k2) or "opencv" (OPENCV: k1, k2, p1, p2).
    distortion: str = "none"
    distortion_k1: float = -0.05
    distortion_k2: float = 0.015
    #: tangential coefficients p1 = p, p2 = -p/2 of the "opencv" model.
    distortion_p: float = 3e-4

    # --- street walk (scene_kind "street") -------------------------------
    #: half side of the square the city is built in, m (the walk is near
    #: its centre; the oblique flight's footprints set it otherwise).
    street_city_half_size_m: float = 150.0
    #: images along the walk and the step between them (the baseline), m.
    street_num_images: int = 36
    street_step_m: float = 2.0
    #: camera height above the terrain, m.
    street_camera_height_m: float = 1.6
    #: horizontal angle of the view forward of the facade normal, and the
    #: upward pitch of the optical axis, degrees.
    street_forward_deg: float = 25.0
    street_pitch_deg: float = 12.0
    #: hand-held irregularity (standard deviations): angles in degrees,
    #: position per axis in metres.
    street_jitter_deg: float = 1.0
    street_jitter_m: float = 0.1
    #: spacing of the ground control points along the street, m.
    street_gcp_spacing_m: float = 30.0

    # --- priors (rough GPS/INS) --------------------------------------------
    #: standard deviation of the prior camera centre per horizontal axis, m.
    prior_position_m: float = 8.0
    #: standard deviation of the prior camera height, m.
    prior_height_m: float = 5.0
    #: standard deviation of each component of the prior rotation error
    #: (axis-angle vector, radians converted from degrees), degrees.
    prior_rotation_deg: float = 1.5
    #: relative focal error per camera, percent: magnitude uniform in
    #: [p/2, p], random sign. Prior principal point = exact image centre.
    prior_focal_percent: float = 3.0
    #: added to every prior camera z (other vertical datum, e.g. ellipsoidal
    #: GPS heights), metres.
    prior_vertical_datum_offset_m: float = 47.0

    # --- terrain -------------------------------------------------------------
    #: slope of the terrain plane, degrees (<= 3 is realistic here).
    slope_deg: float = 1.0
    #: direction of steepest ascent, degrees clockwise from north; None =
    #: drawn from the seed.
    slope_azimuth_deg: float | None = None
    #: amplitude of the sum of low-frequency sinusoids on top of the plane, m.
    undulation_m: float = 1.5
    #: spacing of the terrain mesh, m.
    terrain_spacing_m: float = 10.0
    #: absolute height of the terrain at the scene centre, m.
    ground_height_m: float = 100.0

    # --- city layout -------------------------------------------------------
    #: rotation of the street grid from the east axis, degrees (ccw).
    grid_rotation_deg: float = 17.0
    #: range of block sizes (between property lines), m.
    block_size_min_m: float = 55.0
    block_size_max_m: float = 95.0
    #: range of street widths (property line to property line), m.
    street_width_min_m: float = 12.0
    street_width_max_m: float = 22.0
    #: extra city beyond the union of the camera footprints, m.
    margin_m: float = 60.0
    #: block types drawn (a key of :data:`DISTRICT_BLOCKS`).
    district: str = "mixed"
    #: fraction of streets lined with trees (crowns over the facades' feet).
    street_tree_fraction: float = 0.5

    # --- cadastre ------------------------------------------------------------
    #: fraction of the scene's buildings left out of the map.
    cadastre_missing_fraction: float = 0.03
    #: fraction of mapped buildings that are demolished (not in the scene).
    cadastre_demolished_fraction: float = 0.03
    #: standard deviation of the map's vertex noise per axis, m.
    cadastre_vertex_noise_m: float = 0.15
    #: fraction of mapped buildings shifted as a whole ...
    cadastre_shifted_fraction: float = 0.02
    #: ... by a vector of about this length, m.
    cadastre_shift_m: float = 1.0
    #: fraction of map features that carry a "height" property.
    cadastre_height_fraction: float = 0.7

    # --- georeference --------------------------------------------------------
    crs: str = "EPSG:25832"
    #: absolute easting / northing of the local origin (scene centre), m.
    origin_easting_m: float = 512_340.0
    origin_northing_m: float = 5_643_870.0

    # --- rendering -----------------------------------------------------------
    #: supersampling factor per axis (anti-aliasing).
    supersample: int = 2
    #: standard deviation of the Gaussian optical blur, output pixels.
    blur_sigma_px: float = 0.6
    #: standard deviation of the additive sensor noise, grey levels.
    noise_sigma: float = 2.0
    #: JPEG quality of the written images.
    jpeg_quality: int = 90
    #: sun position: azimuth clockwise from north and elevation, degrees.
    sun_azimuth_deg: float = 150.0
    sun_elevation_deg: float = 45.0
    #: relative brightness fall-off at the image corners.
    vignetting: float = 0.12

    def __post_init__(self) -> None:
        if self.distortion not in DISTORTION_MODELS:
            raise ValueError(
                f"distortion={self.distortion!r}; allowed: "
                f"{', '.join(DISTORTION_MODELS)}"
            )
        if self.scene_kind not in SCENE_KINDS:
            raise ValueError(
                f"scene_kind={self.scene_kind!r}; allowed: {', '.join(SCENE_KINDS)}"
            )
        if self.street_num_images < 2 or self.street_step_m <= 0:
            raise ValueError("street_num_images must be >= 2, street_step_m > 0")
        if self.district not in DISTRICT_BLOCKS:
            raise ValueError(
                f"district={self.district!r}; allowed: {', '.join(DISTRICT_BLOCKS)}"
            )
        if not 0.0 <= self.street_tree_fraction <= 1.0:
            raise ValueError("street_tree_fraction must be in [0, 1]")
        if self.grid_rows < 1 or self.grid_cols < 1:
            raise ValueError("grid_rows and grid_cols must be >= 1")
        if self.image_width_px < 64:
            raise ValueError(f"image_width_px={self.image_width_px} is too small")
        if self.supersample < 1:
            raise ValueError("supersample must be >= 1")
        if not 0.0 <= self.overlap < 0.9:
            raise ValueError(f"overlap={self.overlap} must be in [0, 0.9)")

    @property
    def image_height_px(self) -> int:
        """Image height in pixels."""
        return int(round(self.image_width_px / self.image_aspect))

    @property
    def camera_model(self) -> str:
        """COLMAP model name of the true (and prior) cameras."""
        return DISTORTION_MODELS[self.distortion]

    @property
    def origin(self) -> tuple[float, float, float]:
        """Absolute (x, y, z) of the local origin: ``world_abs = local + origin``."""
        return (self.origin_easting_m, self.origin_northing_m, self.ground_height_m)

    def to_json(self) -> dict:
        return dataclasses.asdict(self)

    @classmethod
    def from_json(cls, data: dict) -> SceneOptions:
        """Inverse of :meth:`to_json`; unknown keys fail and list the allowed."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ValueError(
                f"unknown scene option(s) {unknown}; allowed: {sorted(names)}"
            )
        return cls(**data)


#: Named scenes. ``small`` is for tests (8 images), ``paper`` mirrors the
#: 36-image block of Habbecke & Kobbelt, ``hard`` stresses the priors; the
#: district classes (issue 25's matrix) fly the paper's block over one
#: district each, ``houses`` with the harder flight of detached-house scenes
#: (slope, priors and lens as ``hard``).
PRESETS: dict[str, SceneOptions] = {
    "paper": SceneOptions(),
    "small": SceneOptions(grid_rows=1, grid_cols=2),
}
PRESETS["hard"] = dataclasses.replace(
    PRESETS["paper"],
    slope_deg=3.0,
    prior_position_m=15.0,
    prior_rotation_deg=3.0,
    prior_focal_percent=8.0,
    distortion="radial",
)


PRESETS["dense"] = dataclasses.replace(PRESETS["paper"], district="dense")
PRESETS["houses"] = dataclasses.replace(
    PRESETS["hard"],
    district="houses",
    block_size_min_m=45.0,
    block_size_max_m=75.0,
    street_width_min_m=9.0,
    street_width_max_m=14.0,
    street_tree_fraction=0.8,
)
PRESETS["industrial"] = dataclasses.replace(PRESETS["paper"], district="industrial")
PRESETS["highrise"] = dataclasses.replace(PRESETS["paper"], district="highrise")

#: A phone walking along a street of terraces (issue 27): 4000x3000 sensor
#: rendered at 800x600, about 66 deg across (a 26 mm equivalent lens),
#: SIMPLE_RADIAL; no street trees (the walk is on the sidewalk they stand
#: on); phone-grade priors.
PRESETS["street"] = dataclasses.replace(
    PRESETS["paper"],
    scene_kind="street",
    district="dense",
    street_tree_fraction=0.0,
    image_width_px=800,
    image_aspect=4.0 / 3.0,
    horizontal_fov_deg=66.0,
    principal_point_offset_px=16.0,
    focal_spread=0.0,
    distortion="simple_radial",
    distortion_k1=-0.03,
    terrain_spacing_m=4.0,
    prior_position_m=5.0,
    prior_height_m=5.0,
    prior_rotation_deg=5.0,
)

#: The scene classes of the benchmark matrix (scripts/bench/classes.py).
SCENE_CLASSES = ("paper", "dense", "houses", "industrial", "highrise")


def preset(name: str, **overrides) -> SceneOptions:
    """A preset with some fields replaced; unknown names list the allowed ones."""
    if name not in PRESETS:
        raise ValueError(f"unknown preset {name!r}; allowed: {', '.join(PRESETS)}")
    return dataclasses.replace(PRESETS[name], **overrides)
