"""The synthetic city: terrain, street grid, buildings, clutter and their mesh.

Everything here is in the LOCAL frame (x east, y north, z up, metres;
``world_abs = local + options.origin``) and is a deterministic function of
``(options, seed)``: :func:`build_city` rebuilds exactly the same city from the
values stored in ``scene.json``.

Layout
------
A street grid (rotated by ``grid_rotation_deg``) of blocks between property
lines. Each block is one of: a perimeter terrace (parcels sharing party walls,
L-shaped corner buildings, some skewed party walls), a courtyard building
(polygon with a hole, optionally chamfered corners), detached houses (slightly
rotated rectangles, gabled or hipped roofs, some with a detached annex: a
two-part building), large mixed buildings (L, U, slab, tower, trapezoid, twin
slabs), industrial halls, towers on a plaza (these two in
:mod:`~obliq_colmap.synthetic.districts`) or a park, drawn with the
probabilities of the scene's district (``SceneOptions.district``). Streets
carry lane marks, zebra crossings, parked cars and trees; yards carry sheds
and trees; flat roofs carry small boxes. Only the
buildings are in the cadastre; the rest is unmapped clutter.

Buildings stand on the terrain: ``base_z`` is the minimum terrain height
under the footprint and walls reach 1.5 m below it, so there is never a gap.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
import shapely
from shapely.geometry import MultiPolygon, Polygon
from shapely.geometry.polygon import orient

from obliq_colmap.synthetic.cameras import (
    STREAM_CADASTRE,
    STREAM_CITY,
    city_extent,
    stream,
)
from obliq_colmap.synthetic.districts import DistrictBlocks
from obliq_colmap.synthetic.options import DISTRICT_BLOCKS, SceneOptions

logger = logging.getLogger(__name__)

# Surface materials.
GROUND, WALL, ROOF_FLAT, ROOF_PITCHED, RIM, CAR, TREE, TRUNK, SHED, FLAT = range(10)
MATERIAL_NAMES = (
    "ground",
    "wall",
    "roof_flat",
    "roof_pitched",
    "rim",
    "car",
    "tree",
    "trunk",
    "shed",
    "flat",
)

#: Columns of ``City.surf_style`` (facade layout of a wall, metres / flags).
STYLE_FIELDS = (
    "floor_h",
    "ground_h",
    "win_w",
    "win_h",
    "sill",
    "col_spacing",
    "shop",
    "windows",
)
WINDOW_MARGIN_M = 0.8  # free wall at both ends of a facade
FRAME_M = 0.12  # window frame width
RIM_HEIGHT_M = 0.5  # flat-roof slab above the eave
WALL_BELOW_BASE_M = 1.5  # walls reach this far below base_z
SIDEWALK_M = 2.75

FACADE_COLORS = np.array(
    [
        (0.85, 0.78, 0.65),
        (0.92, 0.88, 0.78),
        (0.90, 0.90, 0.87),
        (0.74, 0.74, 0.73),
        (0.85, 0.68, 0.42),
        (0.86, 0.62, 0.52),
        (0.62, 0.32, 0.24),
        (0.93, 0.86, 0.60),
        (0.68, 0.74, 0.78),
        (0.72, 0.78, 0.66),
        (0.55, 0.42, 0.32),
        (0.66, 0.65, 0.62),
    ]
)
PITCHED_ROOF_COLORS = np.array(
    [
        (0.62, 0.28, 0.18),
        (0.50, 0.24, 0.18),
        (0.30, 0.30, 0.32),
        (0.22, 0.22, 0.24),
        (0.42, 0.30, 0.22),
        (0.35, 0.38, 0.42),
    ]
)
FLAT_ROOF_COLORS = np.array(
    [
        (0.60, 0.58, 0.55),
        (0.32, 0.32, 0.32),
        (0.78, 0.78, 0.76),
        (0.45, 0.52, 0.32),
        (0.52, 0.50, 0.48),
    ]
)
CAR_COLORS = np.array(
    [
        (0.92, 0.92, 0.92),
        (0.08, 0.08, 0.09),
        (0.62, 0.63, 0.66),
        (0.62, 0.08, 0.07),
        (0.12, 0.22, 0.48),
        (0.35, 0.36, 0.38),
        (0.85, 0.82, 0.70),
    ]
)


# --------------------------------------------------------------------------
# Terrain
# --------------------------------------------------------------------------


@dataclass
class Terrain:
    """A regular triangulated height grid; :meth:`height` is exactly the mesh.

    Node (i, j) is at ``(x0 + i * spacing, y0 + j * spacing)`` with height
    ``heights[j, i]``; each cell is split along its (i, j)-(i+1, j+1) diagonal.
    The local origin (0, 0) is a node with height 0.
    """

    x0: float
    y0: float
    spacing: float
    heights: np.ndarray  # (ny, nx)

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Terrain height (local z, m) at local (x, y), same shape as x."""
        x = np.asarray(x, float)
        y = np.asarray(y, float)
        ny, nx = self.heights.shape
        fx = (x - self.x0) / self.spacing
        fy = (y - self.y0) / self.spacing
        i = np.clip(np.floor(fx).astype(int), 0, nx - 2)
        j = np.clip(np.floor(fy).astype(int), 0, ny - 2)
        tx, ty = fx - i, fy - j
        h = self.heights
        h00, h10, h01, h11 = h[j, i], h[j, i + 1], h[j + 1, i], h[j + 1, i + 1]
        lower = tx >= ty
        return np.where(
            lower,
            h00 + tx * (h10 - h00) + ty * (h11 - h10),
            h00 + ty * (h01 - h00) + tx * (h11 - h01),
        )

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """(V, 3) vertices and (F, 3) faces with upward normals."""
        ny, nx = self.heights.shape
        xs = self.x0 + self.spacing * np.arange(nx)
        ys = self.y0 + self.spacing * np.arange(ny)
        X, Y = np.meshgrid(xs, ys)
        verts = np.stack([X.ravel(), Y.ravel(), self.heights.ravel()], 1)
        idx = np.arange(nx * ny).reshape(ny, nx)
        a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
        c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
        # (i,j) (i+1,j) (i+1,j+1) and (i,j) (i+1,j+1) (i,j+1): counter-clockwise.
        faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
        return verts, faces


def make_terrain(options: SceneOptions, rng: np.random.Generator, extent) -> Terrain:
    """Plane of ``slope_deg`` plus a few low-frequency sinusoids."""
    xmin, ymin, xmax, ymax = extent
    pad = 250.0
    s = options.terrain_spacing_m
    i0, i1 = int(np.floor((xmin - pad) / s)), int(np.ceil((xmax + pad) / s))
    j0, j1 = int(np.floor((ymin - pad) / s)), int(np.ceil((ymax + pad) / s))
    xs, ys = s * np.arange(i0, i1 + 1), s * np.arange(j0, j1 + 1)
    X, Y = np.meshgrid(xs, ys)
    az = (
        rng.uniform(0.0, 360.0)
        if options.slope_azimuth_deg is None
        else options.slope_azimuth_deg
    )
    g = np.tan(np.radians(options.slope_deg))
    a = np.radians(az)
    H = g * (X * np.sin(a) + Y * np.cos(a))
    weights = rng.uniform(0.5, 1.0, 3)
    weights *= options.undulation_m / weights.sum()
    for w in weights:
        lam = rng.uniform(250.0, 600.0)
        th = rng.uniform(0.0, np.pi)
        ph = rng.uniform(0.0, 2 * np.pi)
        H = H + w * np.sin(2 * np.pi * (X * np.cos(th) + Y * np.sin(th)) / lam + ph)
    H = H - H[-j0, -i0]  # height 0 at the local origin, which is a node
    return Terrain(float(xs[0]), float(ys[0]), s, H)


# --------------------------------------------------------------------------
# Buildings
# --------------------------------------------------------------------------


@dataclass
class PitchedRoof:
    """Rectangle of a gabled / hipped building: ridge along ``axis``.

    center : (2,) local; axis : (2,) unit ridge direction; length_m along
    the ridge, width_m across; pitch_deg of the roof planes.
    """

    center: np.ndarray
    axis: np.ndarray
    length_m: float
    width_m: float
    pitch_deg: float


@dataclass
class Building:
    """One building of the city (in the scene and/or in the map).

    Attributes
    ----------
    id : int, shared with the cadastre feature.
    footprint : shapely Polygon or MultiPolygon, local frame, WALL footprint
        (exterior rings counter-clockwise).
    height_m : wall (eave) height above ``base_z``, m.
    base_z : minimum terrain height under the footprint, local m.
    roof : "flat", "gabled" or "hipped"; pitched roofs have ``pitched``.
    overhang_m : horizontal roof overhang beyond the walls, m.
    in_scene, in_map, shift_m : cadastre discrepancies.
    style : (8,) facade layout, see :data:`STYLE_FIELDS`.
    """

    id: int
    footprint: Polygon | MultiPolygon
    height_m: float
    roof: str = "flat"
    pitched: PitchedRoof | None = None
    overhang_m: float = 0.0
    base_z: float = 0.0
    in_scene: bool = True
    in_map: bool = True
    shift_m: tuple[float, float] = (0.0, 0.0)
    style: np.ndarray = field(default_factory=lambda: np.zeros(8))
    facade_color: np.ndarray = field(default_factory=lambda: np.ones(3))
    frame_color: np.ndarray = field(default_factory=lambda: np.ones(3))
    roof_color: np.ndarray = field(default_factory=lambda: np.ones(3))
    rim_color: np.ndarray = field(default_factory=lambda: np.ones(3))

    @property
    def parts(self) -> list[Polygon]:
        if isinstance(self.footprint, MultiPolygon):
            return list(self.footprint.geoms)
        return [self.footprint]

    @property
    def ridge_height_m(self) -> float:
        """Height of the ridge above ``base_z`` (= height_m for flat roofs)."""
        if self.pitched is None:
            return self.height_m + RIM_HEIGHT_M
        p = self.pitched
        return self.height_m + 0.5 * p.width_m * np.tan(np.radians(p.pitch_deg))

    def ridge_points(self) -> np.ndarray:
        """(2, 3) local ridge ends of a pitched roof, (0, 3) for flat roofs."""
        if self.pitched is None:
            return np.zeros((0, 3))
        p = self.pitched
        half = 0.5 * p.length_m
        if self.roof == "hipped":
            half = 0.5 * (p.length_m - p.width_m)
        z = self.base_z + self.ridge_height_m
        return np.array(
            [[*(p.center - half * p.axis), z], [*(p.center + half * p.axis), z]]
        )


@dataclass
class Layout:
    """Street grid in the grid frame: ``local = rot(theta) @ grid``."""

    theta: float  # radians
    xs: np.ndarray  # street centre lines x = xs[k] (grid frame)
    wx: np.ndarray  # their widths
    ys: np.ndarray
    wy: np.ndarray
    block_kind: (
        np.ndarray
    )  # (len(ys) - 1, len(xs) - 1) int: yard style (0 paved, 1 green)

    def to_local(self, g: np.ndarray) -> np.ndarray:
        c, s = np.cos(self.theta), np.sin(self.theta)
        g = np.asarray(g, float)
        return np.stack(
            [c * g[..., 0] - s * g[..., 1], s * g[..., 0] + c * g[..., 1]], -1
        )

    def to_grid(self, p: np.ndarray) -> np.ndarray:
        c, s = np.cos(self.theta), np.sin(self.theta)
        p = np.asarray(p, float)
        return np.stack(
            [c * p[..., 0] + s * p[..., 1], -s * p[..., 0] + c * p[..., 1]], -1
        )


@dataclass
class City:
    """The full synthetic city: terrain, layout, buildings and a triangle mesh.

    Mesh arrays (local frame): ``vertices`` (V, 3) float64, ``faces`` (F, 3)
    int32 with outward normals ``face_normal`` (F, 3), ``face_surface`` (F,)
    into the surface table ``surf_*`` (S, ...) that maps a 3D point to texture
    coordinates ``u = (P - origin) . u_axis``, ``v = (P - origin) . v_axis``.
    ``boxes`` (B, 4, 2) footprints and ``box_z`` (B, 2) of box clutter (for
    clutter vertical edges).
    """

    options: SceneOptions
    seed: int
    extent: tuple[float, float, float, float]
    terrain: Terrain
    layout: Layout
    buildings: list[Building]
    vertices: np.ndarray
    faces: np.ndarray
    face_normal: np.ndarray
    face_surface: np.ndarray
    surf_material: np.ndarray
    surf_object: np.ndarray
    surf_origin: np.ndarray
    surf_u: np.ndarray
    surf_v: np.ndarray
    surf_length: np.ndarray
    surf_height: np.ndarray
    surf_color: np.ndarray
    surf_color2: np.ndarray
    surf_style: np.ndarray
    surf_seed: np.ndarray
    boxes: np.ndarray
    box_z: np.ndarray

    @property
    def origin(self) -> np.ndarray:
        return np.asarray(self.options.origin, float)

    def building_by_id(self, building_id: int) -> Building:
        for b in self.buildings:
            if b.id == building_id:
                return b
        raise KeyError(building_id)

    @property
    def face_material(self) -> np.ndarray:
        return self.surf_material[self.face_surface]


# --------------------------------------------------------------------------
# Mesh assembly
# --------------------------------------------------------------------------


class _MeshBuilder:
    """Collects triangles (each with its own 3 vertices) and surfaces."""

    def __init__(self) -> None:
        self.tris: list[np.ndarray] = []  # (m, 3, 3)
        self.tri_surf: list[np.ndarray] = []
        self.tri_hint: list[np.ndarray] = []  # (m, 3); zero: no hint
        self.surf: dict[str, list] = {
            k: []
            for k in (
                "material",
                "object",
                "origin",
                "u",
                "v",
                "length",
                "height",
                "color",
                "color2",
                "style",
                "seed",
            )
        }

    def surface(
        self,
        material,
        obj=-1,
        origin=(0, 0, 0),
        u=(1, 0, 0),
        v=(0, 1, 0),
        color=(0.5, 0.5, 0.5),
        color2=(0.5, 0.5, 0.5),
        length=0.0,
        height=0.0,
        style=None,
        seed=0,
    ) -> int:
        s = self.surf
        s["material"].append(material)
        s["object"].append(obj)
        s["origin"].append(np.asarray(origin, float))
        s["u"].append(np.asarray(u, float))
        s["v"].append(np.asarray(v, float))
        s["length"].append(float(length))
        s["height"].append(float(height))
        s["color"].append(np.asarray(color, float))
        s["color2"].append(np.asarray(color2, float))
        s["style"].append(np.zeros(8) if style is None else np.asarray(style, float))
        s["seed"].append(int(seed) & 0xFFFFFFFF)
        return len(s["material"]) - 1

    def triangles(self, tris: np.ndarray, surf, normal_hint: np.ndarray | None = None):
        """Add (m, 3, 3) triangles; those whose normal opposes the hint (3,)
        or (m, 3) are flipped in :meth:`oriented` (one pass over the whole
        mesh: a building adds its walls a few triangles at a time)."""
        tris = np.asarray(tris, float).reshape(-1, 3, 3)
        self.tris.append(tris)
        self.tri_surf.append(
            np.broadcast_to(np.asarray(surf, np.int32), (len(tris),)).copy()
        )
        hint = np.zeros(3) if normal_hint is None else normal_hint
        self.tri_hint.append(np.broadcast_to(np.asarray(hint, float), (len(tris), 3)))

    def oriented(self) -> np.ndarray:
        """(T, 3, 3) every triangle added, wound so that its normal does not
        oppose its hint (triangles without a hint as given)."""
        tris = np.concatenate(self.tris)
        hint = np.concatenate(self.tri_hint)
        n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
        flip = np.einsum("ij,ij->i", n, hint) < 0
        tris[flip] = tris[flip][:, [0, 2, 1]]
        return tris

    def convex(self, pts: np.ndarray, surf: int, normal_hint) -> None:
        """Fan-triangulate a convex planar polygon (n, 3)."""
        pts = np.asarray(pts, float)
        n = len(pts)
        tris = np.stack([np.repeat(pts[:1], n - 2, 0), pts[1:-1], pts[2:]], 1)
        self.triangles(tris, surf, normal_hint)


def _triangulate(poly: Polygon) -> np.ndarray:
    """(m, 3, 2) triangles of a polygon with holes (constrained Delaunay)."""
    if len(poly.interiors) == 0 and len(poly.exterior.coords) == 5:
        c = np.asarray(poly.exterior.coords)[:4]
        return np.stack([c[[0, 1, 2]], c[[0, 2, 3]]])
    tris = shapely.constrained_delaunay_triangles(poly)
    out = [np.asarray(t.exterior.coords)[:3] for t in tris.geoms]
    return np.asarray(out).reshape(-1, 3, 2)


def _rings(poly: Polygon) -> list[np.ndarray]:
    """Rings (n, 2) without the closing point, interior on the left."""
    poly = orient(poly, 1.0)
    rings = [np.asarray(poly.exterior.coords)[:-1]]
    rings += [np.asarray(r.coords)[:-1] for r in poly.interiors]
    return rings


def _add_building_mesh(mb: _MeshBuilder, b: Building) -> None:
    z_eave = b.base_z + b.height_m
    z_bot = b.base_z - WALL_BELOW_BASE_M
    seed = (b.id * 7919) & 0xFFFFFFFF
    wall_rng = np.random.default_rng(b.id)
    for part in b.parts:
        for ring in _rings(part):
            nxt = np.roll(ring, -1, axis=0)
            for k, (A, B) in enumerate(zip(ring, nxt, strict=True)):
                d = B - A
                L = float(np.hypot(*d))
                if L < 1e-6:
                    continue
                u = np.array([d[0] / L, d[1] / L, 0.0])
                out = np.array([u[1], -u[0], 0.0])
                shade = 1.0 + wall_rng.uniform(-0.06, 0.06)
                style = b.style.copy()
                style[7] = 1.0 if 2 * WINDOW_MARGIN_M + style[2] <= L else 0.0
                s = mb.surface(
                    WALL,
                    b.id,
                    (A[0], A[1], b.base_z),
                    u,
                    (0, 0, 1),
                    np.clip(b.facade_color * shade, 0, 1),
                    b.frame_color,
                    L,
                    b.height_m,
                    style,
                    seed + 131 * k,
                )
                quad = np.array(
                    [
                        [A[0], A[1], z_bot],
                        [B[0], B[1], z_bot],
                        [B[0], B[1], z_eave],
                        [A[0], A[1], z_eave],
                    ]
                )
                mb.convex(quad, s, out)
    if b.roof == "flat":
        _add_flat_roof(mb, b, z_eave)
    else:
        _add_pitched_roof(mb, b, z_eave)


def _add_flat_roof(mb: _MeshBuilder, b: Building, z_eave: float) -> None:
    z_top = z_eave + RIM_HEIGHT_M
    roof = b.footprint
    if b.overhang_m > 0:
        roof = roof.buffer(b.overhang_m, join_style="mitre", mitre_limit=3.0)
    z_rim0 = z_eave - (0.2 if b.overhang_m > 0 else 0.0)
    parts = list(roof.geoms) if isinstance(roof, MultiPolygon) else [roof]
    s_top = mb.surface(
        ROOF_FLAT,
        b.id,
        (0, 0, z_top),
        (1, 0, 0),
        (0, 1, 0),
        b.roof_color,
        b.rim_color,
        seed=b.id * 31,
    )
    s_rim = mb.surface(
        RIM,
        b.id,
        (0, 0, z_eave),
        (1, 0, 0),
        (0, 0, 1),
        b.rim_color,
        b.rim_color,
        seed=b.id * 37,
    )
    for part in parts:
        t2 = _triangulate(part)
        tris = np.concatenate([t2, np.full(t2.shape[:2] + (1,), z_top)], -1)
        mb.triangles(tris, s_top, (0, 0, 1))
        for ring in _rings(part):
            nxt = np.roll(ring, -1, axis=0)
            d = nxt - ring
            out = np.stack([d[:, 1], -d[:, 0], np.zeros(len(d))], 1)
            quads = np.stack(
                [
                    np.column_stack([ring, np.full(len(ring), z_rim0)]),
                    np.column_stack([nxt, np.full(len(ring), z_rim0)]),
                    np.column_stack([nxt, np.full(len(ring), z_top)]),
                    np.column_stack([ring, np.full(len(ring), z_top)]),
                ],
                1,
            )  # (n, 4, 3)
            tris = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]])
            mb.triangles(tris, s_rim, np.concatenate([out, out]))


def _add_pitched_roof(mb: _MeshBuilder, b: Building, z_eave: float) -> None:
    p = b.pitched
    assert p is not None
    t = np.tan(np.radians(p.pitch_deg))
    u = np.array([p.axis[0], p.axis[1], 0.0])
    v = np.array([-p.axis[1], p.axis[0], 0.0])
    c = np.array([p.center[0], p.center[1], 0.0])
    hl, hw, o = 0.5 * p.length_m, 0.5 * p.width_m, b.overhang_m
    z_ridge = z_eave + hw * t
    z_low = z_eave - o * t
    ridge_half = hl + o if b.roof == "gabled" else hl - hw

    def P(a, bb, z):
        return c + a * u + bb * v + np.array([0, 0, z])

    for side in (1.0, -1.0):
        down = side * v * np.cos(np.arctan(t)) - np.array([0, 0, np.sin(np.arctan(t))])
        origin = P(-ridge_half, 0, z_ridge)
        s = mb.surface(
            ROOF_PITCHED,
            b.id,
            origin,
            u,
            down,
            b.roof_color,
            b.rim_color,
            seed=b.id * 41 + int(side > 0),
        )
        quad = [
            P(-ridge_half, 0, z_ridge),
            P(ridge_half, 0, z_ridge),
            P(hl + o, side * (hw + o), z_low),
            P(-hl - o, side * (hw + o), z_low),
        ]
        normal = side * v * t + np.array([0, 0, 1.0])
        mb.convex(np.array(quad), s, normal)
    for end in (1.0, -1.0):
        if b.roof == "hipped":
            down = end * u * np.cos(np.arctan(t)) - np.array(
                [0, 0, np.sin(np.arctan(t))]
            )
            s = mb.surface(
                ROOF_PITCHED,
                b.id,
                P(end * ridge_half, 0, z_ridge),
                v,
                down,
                b.roof_color,
                b.rim_color,
                seed=b.id * 43 + int(end > 0),
            )
            tri = [
                P(end * ridge_half, 0, z_ridge),
                P(end * (hl + o), hw + o, z_low),
                P(end * (hl + o), -(hw + o), z_low),
            ]
            mb.convex(np.array(tri), s, end * u * t + np.array([0, 0, 1.0]))
        else:  # gable wall triangle, in the end wall's plane
            A = P(end * hl, -end * hw, z_eave)
            s = mb.surface(
                WALL,
                b.id,
                (A[0], A[1], b.base_z),
                end * v,
                (0, 0, 1),
                b.facade_color,
                b.frame_color,
                p.width_m,
                b.height_m,
                np.zeros(8),
                b.id,
            )
            tri = [A, P(end * hl, end * hw, z_eave), P(end * hl, 0, z_ridge)]
            mb.convex(np.array(tri), s, end * u)


def _unit_sphere(n_az: int = 8, n_el: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """(m, 3, 3) triangles of a low-poly unit sphere with outward winding."""
    az = np.linspace(0, 2 * np.pi, n_az + 1)
    el = np.linspace(-np.pi / 2, np.pi / 2, n_el + 1)
    tris = []
    for i in range(n_el):
        for j in range(n_az):
            p = [
                (
                    np.cos(el[a]) * np.cos(az[b]),
                    np.cos(el[a]) * np.sin(az[b]),
                    np.sin(el[a]),
                )
                for a, b in ((i, j), (i, j + 1), (i + 1, j + 1), (i + 1, j))
            ]
            if i > 0:
                tris.append([p[0], p[1], p[2]])
            if i < n_el - 1:
                tris.append([p[0], p[2], p[3]])
    tris = np.array(tris)
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    flip = np.einsum("ij,ij->i", n, tris.mean(1)) < 0
    tris[flip] = tris[flip][:, [0, 2, 1]]
    return tris


def _unit_cone(n: int = 8) -> np.ndarray:
    """(n, 3, 3) side triangles of a cone of radius 1, height 1, outward."""
    az = np.linspace(0, 2 * np.pi, n + 1)
    tris = [
        [
            (np.cos(az[j]), np.sin(az[j]), 0.0),
            (np.cos(az[j + 1]), np.sin(az[j + 1]), 0.0),
            (0.0, 0.0, 1.0),
        ]
        for j in range(n)
    ]
    return np.array(tris)


def _box_tris(
    corners: np.ndarray, z0: float, z1: float, top: bool = True
) -> np.ndarray:
    """(m, 3, 3) triangles (4 walls + top) of a box with (4, 2) ccw corners."""
    tris = []
    for k in range(4):
        A, B = corners[k], corners[(k + 1) % 4]
        q = [(A[0], A[1], z0), (B[0], B[1], z0), (B[0], B[1], z1), (A[0], A[1], z1)]
        tris += [[q[0], q[1], q[2]], [q[0], q[2], q[3]]]
    if top:
        t = [(c[0], c[1], z1) for c in corners]
        tris += [[t[0], t[1], t[2]], [t[0], t[2], t[3]]]
    return np.array(tris)


def _rect(center, axis, length, width) -> np.ndarray:
    """(4, 2) counter-clockwise corners of an oriented rectangle."""
    center = np.asarray(center, float)
    u = np.asarray(axis, float) / np.linalg.norm(axis)
    v = np.array([-u[1], u[0]])
    hl, hw = 0.5 * length, 0.5 * width
    return np.array(
        [
            center - hl * u - hw * v,
            center + hl * u - hw * v,
            center + hl * u + hw * v,
            center - hl * u + hw * v,
        ]
    )


# --------------------------------------------------------------------------
# Layout and blocks
# --------------------------------------------------------------------------


def _street_lines(
    lo: float, hi: float, rng, o: SceneOptions
) -> tuple[np.ndarray, np.ndarray]:
    def width():
        if rng.uniform() < 0.3:
            return rng.uniform(0.8 * o.street_width_max_m, o.street_width_max_m)
        return rng.uniform(
            o.street_width_min_m,
            0.7 * (o.street_width_min_m + o.street_width_max_m) / 2
            + 0.3 * o.street_width_min_m,
        )

    xs, ws = [lo - 30.0], [width()]
    while xs[-1] < hi + 30.0:
        w = width()
        xs.append(
            xs[-1]
            + ws[-1] / 2
            + rng.uniform(o.block_size_min_m, o.block_size_max_m)
            + w / 2
        )
        ws.append(w)
    return np.array(xs), np.array(ws)


class _CityBuilder(DistrictBlocks):
    """Fills blocks with buildings and clutter (grid-frame generation)."""

    def __init__(self, options: SceneOptions, rng: np.random.Generator, layout: Layout):
        self.o = options
        self.rng = rng
        self.layout = layout
        self.buildings: list[Building] = []
        self.trees: list[
            tuple[float, float, float, float, int]
        ] = []  # gx, gy, r, h, kind
        self.boxes: list[tuple[np.ndarray, float, float, int, np.ndarray]] = []
        # box: (4,2) grid corners, z offset base, height, material, colour
        self.roof_boxes: list[tuple[int, np.ndarray, float]] = []
        self.next_id = 1001

    # ---- buildings -------------------------------------------------------
    def _style(self, height: float, shop: bool) -> np.ndarray:
        r = self.rng
        floor_h = r.uniform(2.9, 3.6)
        ground_h = r.uniform(3.8, 4.6) if shop else floor_h
        win_w = r.uniform(1.0, 1.6)
        col = r.uniform(win_w + 1.0, win_w + 2.6)
        win_h = r.uniform(1.3, min(1.9, floor_h - 1.2))
        sill = r.uniform(0.8, floor_h - win_h - 0.3)
        return np.array([floor_h, ground_h, win_w, win_h, sill, col, float(shop), 1.0])

    def add_building(
        self,
        poly_grid,
        height,
        roof="flat",
        pitched_grid=None,
        overhang=0.0,
        shop_p=0.3,
    ) -> Building:
        """``poly_grid``: Polygon/MultiPolygon in the grid frame."""
        r = self.rng
        if isinstance(poly_grid, MultiPolygon):
            parts = [self._poly_to_local(p) for p in poly_grid.geoms]
            fp = MultiPolygon(parts)
        else:
            fp = self._poly_to_local(poly_grid)
        pitched = None
        if pitched_grid is not None:
            cg, ax, L, W, pitch = pitched_grid
            c = self.layout.to_local(np.asarray(cg, float))
            a = self.layout.to_local(np.asarray(ax, float))
            pitched = PitchedRoof(
                c, a / np.linalg.norm(a), float(L), float(W), float(pitch)
            )
        fc = FACADE_COLORS[r.integers(len(FACADE_COLORS))] * r.uniform(0.93, 1.05, 3)
        frame = (
            np.array([0.95, 0.95, 0.93])
            if r.uniform() < 0.7
            else np.array([0.25, 0.25, 0.27])
        )
        if pitched is not None:
            rc = PITCHED_ROOF_COLORS[r.integers(len(PITCHED_ROOF_COLORS))]
        else:
            rc = FLAT_ROOF_COLORS[r.integers(len(FLAT_ROOF_COLORS))]
        rc = rc * r.uniform(0.92, 1.08, 3)
        rim = (
            np.clip(fc * r.choice([0.7, 1.15]), 0, 1)
            if r.uniform() < 0.6
            else np.array([0.85, 0.85, 0.83])
        )
        b = Building(
            id=self.next_id,
            footprint=fp,
            height_m=float(height),
            roof=roof,
            pitched=pitched,
            overhang_m=float(overhang),
            style=self._style(height, bool(r.uniform() < shop_p and height > 8)),
            facade_color=np.clip(fc, 0, 1),
            frame_color=frame,
            roof_color=np.clip(rc, 0, 1),
            rim_color=rim,
        )
        self.next_id += 1
        self.buildings.append(b)
        return b

    def _poly_to_local(self, p: Polygon) -> Polygon:
        ext = self.layout.to_local(np.asarray(p.exterior.coords))
        holes = [self.layout.to_local(np.asarray(h.coords)) for h in p.interiors]
        return orient(Polygon(ext, holes), 1.0)

    def floors(self, lo, hi):
        return float(np.round(self.rng.uniform(lo, hi) / 0.5) * 0.5)

    # ---- block types -----------------------------------------------------
    def block(self, x0, y0, x1, y1, kx, ky) -> int:
        r = self.rng
        kinds = DISTRICT_BLOCKS[self.o.district]
        kind = r.choice(list(kinds), p=list(kinds.values()))
        getattr(self, f"_{kind}")(x0, y0, x1, y1)
        return 1 if kind in ("houses", "park") or r.uniform() < 0.3 else 0

    def _terrace(self, x0, y0, x1, y1):
        r = self.rng
        bw, bh = x1 - x0, y1 - y0
        d = min(r.uniform(10.0, 14.0), (min(bw, bh) - 14.0) / 2)
        h0 = r.uniform(11.0, 22.0)
        gabled_block = r.uniform() < 0.45
        origins = [
            np.array([x0, y0]),
            np.array([x1, y0]),
            np.array([x1, y1]),
            np.array([x0, y1]),
        ]
        es = [
            np.array([1.0, 0]),
            np.array([0, 1.0]),
            np.array([-1.0, 0]),
            np.array([0, -1.0]),
        ]
        lens = [bw, bh, bw, bh]
        arm_along = r.uniform(3.0, 9.0, 4)
        arm_back = r.uniform(3.0, 9.0, 4)
        for i in range(4):
            F, e = origins[i], es[i]
            n = np.array([-e[1], e[0]])

            def pt(a, s, F=F, e=e, n=n):
                return F + a * e + s * n

            # Corner building at the start of side i (L-shaped, flat roof).
            ring = [
                pt(0, 0),
                pt(d + arm_along[i], 0),
                pt(d + arm_along[i], d),
                pt(d, d),
                pt(d, d + arm_back[i]),
                pt(0, d + arm_back[i]),
            ]
            self.add_building(Polygon(ring), self.floors(h0, h0 + 6), shop_p=0.6)
            a0 = d + arm_along[i]
            a1 = lens[i] - d - arm_back[(i + 1) % 4]
            cuts = [a0]
            while cuts[-1] < a1 - 1e-6:
                w = r.uniform(7.0, 16.0)
                if a1 - (cuts[-1] + w) < 6.0:
                    w = a1 - cuts[-1]
                cuts.append(cuts[-1] + w)
            skew = (
                [0.0]
                + [
                    (
                        r.uniform(-2.0, 2.0)
                        if (not gabled_block and r.uniform() < 0.35)
                        else 0.0
                    )
                    for _ in cuts[1:-1]
                ]
                + [0.0]
            )
            for k in range(len(cuts) - 1):
                a, b_ = cuts[k], cuts[k + 1]
                ring = [
                    pt(a, 0),
                    pt(b_, 0),
                    pt(b_ + skew[k + 1], d),
                    pt(a + skew[k], d),
                ]
                h = self.floors(h0 - 3, h0 + 5)
                rect = skew[k] == 0 and skew[k + 1] == 0
                if gabled_block and rect and r.uniform() < 0.85:
                    c = pt((a + b_) / 2, d / 2)
                    pitch = r.uniform(35, 48)
                    self.add_building(
                        Polygon(ring), h, "gabled", (c, e, b_ - a, d, pitch)
                    )
                else:
                    self.add_building(Polygon(ring), h, shop_p=0.45)
        # Yard: rear building, sheds and trees.
        yx0, yy0, yx1, yy1 = x0 + d + 3, y0 + d + 3, x1 - d - 3, y1 - d - 3
        if r.uniform() < 0.35 and yx1 - yx0 > 16 and yy1 - yy0 > 16:
            L = r.uniform(12, min(25, yx1 - yx0 - 2))
            W = r.uniform(8, min(11, yy1 - yy0 - 6))
            cx = r.uniform(yx0 + L / 2, yx1 - L / 2)
            cy = r.uniform(yy0 + W / 2, yy1 - W / 2)
            ring = _rect((cx, cy), (1, 0), L, W)
            if r.uniform() < 0.5:
                self.add_building(
                    Polygon(ring),
                    self.floors(7, 12),
                    "gabled",
                    ((cx, cy), (1, 0), L, W, r.uniform(30, 42)),
                    0.3,
                )
            else:
                self.add_building(Polygon(ring), self.floors(6, 12), shop_p=0)
        self._yard_clutter(
            yx0, yy0, yx1, yy1, n_trees=r.integers(0, 6), n_sheds=r.integers(0, 3)
        )

    def _courtyard(self, x0, y0, x1, y1):
        r = self.rng
        c = r.uniform(3.0, 8.0) if r.uniform() < 0.5 else 0.0
        ext = [
            (x0 + c, y0),
            (x1 - c, y0),
            (x1, y0 + c),
            (x1, y1 - c),
            (x1 - c, y1),
            (x0 + c, y1),
            (x0, y1 - c),
            (x0, y0 + c),
        ]
        ext = [p for i, p in enumerate(ext) if c > 0 or i % 2 == 0]
        d = r.uniform(11.0, 15.0)
        hole = [(x0 + d, y0 + d), (x0 + d, y1 - d), (x1 - d, y1 - d), (x1 - d, y0 + d)]
        self.add_building(Polygon(ext, [hole]), self.floors(14, 28), shop_p=0.5)
        self._yard_clutter(
            x0 + d + 2,
            y0 + d + 2,
            x1 - d - 2,
            y1 - d - 2,
            n_trees=r.integers(1, 6),
            n_sheds=r.integers(0, 2),
        )

    def _houses(self, x0, y0, x1, y1):
        r = self.rng
        bw, bh = x1 - x0, y1 - y0
        nx = max(1, int(round(bw / r.uniform(18, 24))))
        ny = max(1, int(round(bh / r.uniform(18, 24))))
        lw, lh = bw / nx, bh / ny
        for i in range(nx):
            for j in range(ny):
                lx0, ly0 = x0 + i * lw, y0 + j * lh
                if r.uniform() < 0.08:
                    self._yard_clutter(
                        lx0 + 1, ly0 + 1, lx0 + lw - 1, ly0 + lh - 1, 3, 0
                    )
                    continue
                L = min(r.uniform(9, 14), lw - 6)
                W = min(r.uniform(7.5, 11), lh - 6, L - 1.0)
                if W < 6:
                    continue
                phi = np.radians(r.uniform(-8, 8))
                axis = np.array([np.cos(phi), np.sin(phi)])
                center = np.array([lx0 + lw / 2, ly0 + lh / 2]) + r.uniform(-1, 1, 2)
                ring = _rect(center, axis, L, W)
                pitch = r.uniform(30, 45)
                overhang = r.uniform(0.2, 0.5)
                u = r.uniform()
                if u < 0.1 and lw - L > 8:
                    # Two-part building: house + detached annex (one map feature).
                    side = 1.0 if r.uniform() < 0.5 else -1.0
                    ac = center + side * axis * (L / 2 + 2.0 + 1.75)
                    annex = _rect(ac, axis, 3.5, 6.0)
                    mp = MultiPolygon([Polygon(ring), Polygon(annex)])
                    if Polygon(annex).within(
                        Polygon(
                            [
                                (lx0, ly0),
                                (lx0 + lw, ly0),
                                (lx0 + lw, ly0 + lh),
                                (lx0, ly0 + lh),
                            ]
                        )
                    ):
                        self.add_building(mp, self.floors(6, 7), overhang=0.0, shop_p=0)
                    else:
                        self.add_building(Polygon(ring), self.floors(6, 8.5), shop_p=0)
                elif u < 0.55:
                    self.add_building(
                        Polygon(ring),
                        self.floors(6, 8.5),
                        "gabled",
                        (center, axis, L, W, pitch),
                        overhang,
                        shop_p=0,
                    )
                elif u < 0.92:
                    self.add_building(
                        Polygon(ring),
                        self.floors(6, 8.5),
                        "hipped",
                        (center, axis, L, W, pitch - 8),
                        overhang,
                        shop_p=0,
                    )
                else:
                    self.add_building(
                        Polygon(ring), self.floors(6, 9), overhang=overhang, shop_p=0
                    )
                self._lot_clutter(lx0, ly0, lw, lh, ring)

    def _mixed(self, x0, y0, x1, y1):
        r = self.rng
        bw, bh = x1 - x0, y1 - y0
        along_x = bw >= bh
        n = 2 if (bw if along_x else bh) < 75 else int(r.integers(2, 4))
        cuts = (
            np.sort(r.uniform(0.35, 0.65, n - 1))
            if n == 2
            else np.array([1 / 3, 2 / 3]) + r.uniform(-0.05, 0.05, 2)
        )
        edges = np.concatenate([[0.0], cuts, [1.0]])
        for k in range(n):
            if along_x:
                sx0, sx1, sy0, sy1 = x0 + edges[k] * bw, x0 + edges[k + 1] * bw, y0, y1
            else:
                sx0, sx1, sy0, sy1 = x0, x1, y0 + edges[k] * bh, y0 + edges[k + 1] * bh
            sb = r.uniform(0.0, 4.0, 4)
            gap = 2.5
            rx0 = sx0 + (sb[0] if k == 0 or not along_x else gap)
            rx1 = sx1 - (sb[1] if k == n - 1 or not along_x else gap)
            ry0 = sy0 + (sb[2] if k == 0 or along_x else gap)
            ry1 = sy1 - (sb[3] if k == n - 1 or along_x else gap)
            self._mixed_shape(rx0, ry0, rx1, ry1)

    def _mixed_shape(self, x0, y0, x1, y1):
        r = self.rng
        a, b = x1 - x0, y1 - y0
        if a < 12 or b < 12:
            return
        flipx, flipy = r.uniform() < 0.5, r.uniform() < 0.5

        def P(pts):
            pts = np.asarray(pts, float)
            pts[:, 0] = a - pts[:, 0] if flipx else pts[:, 0]
            pts[:, 1] = b - pts[:, 1] if flipy else pts[:, 1]
            return orient(Polygon(pts + [x0, y0]), 1.0)

        overhang = r.uniform(0.0, 0.5) if r.uniform() < 0.5 else 0.0
        kind = r.choice(
            ["L", "U", "slab", "tower", "trapezoid", "twin"],
            p=[0.25, 0.18, 0.2, 0.15, 0.12, 0.1],
        )
        t = min(r.uniform(10, 15), min(a, b) - 4)
        if kind == "L" and min(a, b) > t + 6:
            self.add_building(
                P([(0, 0), (a, 0), (a, t), (t, t), (t, b), (0, b)]),
                self.floors(10, 30),
                overhang=overhang,
            )
        elif kind == "U" and a > 2 * t + 6 and b > t + 6:
            self.add_building(
                P(
                    [
                        (0, 0),
                        (a, 0),
                        (a, b),
                        (a - t, b),
                        (a - t, t),
                        (t, t),
                        (t, b),
                        (0, b),
                    ]
                ),
                self.floors(10, 28),
                overhang=overhang,
            )
        elif kind == "tower":
            s = min(r.uniform(16, 24), a, b)
            cx, cy = r.uniform(s / 2, a - s / 2), r.uniform(s / 2, b - s / 2)
            self.add_building(
                P(_rect((cx, cy), (1, 0), s, s)),
                self.floors(30, 45),
                overhang=overhang,
                shop_p=0.6,
            )
            self._yard_clutter(x0, y0, x1, y1, n_trees=r.integers(0, 4), n_sheds=0)
        elif kind == "trapezoid":
            d1, d2 = r.uniform(2, min(9, a / 4), 2)
            self.add_building(
                P([(0, 0), (a, 0), (a - d1, b), (d2, b)]),
                self.floors(10, 26),
                overhang=overhang,
            )
        elif kind == "twin" and min(a, b) > 20:
            g = 6.0
            if a >= b:
                w = (b - g) / 2
                p1, p2 = (
                    P([(0, 0), (a, 0), (a, w), (0, w)]),
                    P([(0, w + g), (a, w + g), (a, b), (0, b)]),
                )
            else:
                w = (a - g) / 2
                p1, p2 = (
                    P([(0, 0), (w, 0), (w, b), (0, b)]),
                    P([(w + g, 0), (a, 0), (a, b), (w + g, b)]),
                )
            self.add_building(MultiPolygon([p1, p2]), self.floors(8, 20), overhang=0.0)
        else:  # slab
            L, W = (
                (a, min(b, r.uniform(11, 16)))
                if a >= b
                else (min(a, r.uniform(11, 16)), b)
            )
            cx, cy = (
                r.uniform(L / 2, a - L / 2 + 1e-9),
                r.uniform(W / 2, b - W / 2 + 1e-9),
            )
            axis = (1.0, 0.0) if L >= W else (0.0, 1.0)
            Ll, Ww = max(L, W), min(L, W)
            ring = P(_rect((cx, cy), (1, 0), L, W))
            roof = r.choice(["flat", "hipped", "gabled"], p=[0.5, 0.3, 0.2])
            c = np.asarray(ring.centroid.coords[0])
            if roof == "flat" or Ll < Ww + 1.5:
                self.add_building(ring, self.floors(10, 30), overhang=overhang)
            else:
                self.add_building(
                    ring,
                    self.floors(8, 20),
                    roof,
                    (c, axis, Ll, Ww, r.uniform(25, 38)),
                    overhang,
                )
            self._yard_clutter(x0, y0, x1, y1, n_trees=r.integers(0, 4), n_sheds=0)

    def _park(self, x0, y0, x1, y1):
        r = self.rng
        n = int((x1 - x0) * (y1 - y0) / 120)
        self._yard_clutter(
            x0 + 2, y0 + 2, x1 - 2, y1 - 2, n_trees=n, n_sheds=r.integers(0, 2)
        )

    # ---- clutter ---------------------------------------------------------
    def _free(self, pts_grid: np.ndarray, clearance: float) -> np.ndarray:
        """Mask of grid points at least ``clearance`` away from recent buildings."""
        if not self.buildings:
            return np.ones(len(pts_grid), bool)
        recent = [b.footprint for b in self.buildings[-12:]]
        u = shapely.union_all(recent).buffer(clearance)
        loc = self.layout.to_local(pts_grid)
        return ~shapely.contains_xy(u, loc[:, 0], loc[:, 1])

    def _yard_clutter(self, x0, y0, x1, y1, n_trees, n_sheds):
        r = self.rng
        if x1 - x0 < 4 or y1 - y0 < 4:
            return
        if n_trees:
            pts = np.column_stack(
                [r.uniform(x0, x1, n_trees), r.uniform(y0, y1, n_trees)]
            )
            for p in pts[self._free(pts, 3.0)]:
                self._tree(p)
        for _ in range(int(n_sheds)):
            c = np.array([r.uniform(x0 + 3, x1 - 3), r.uniform(y0 + 3, y1 - 3)])
            if x1 - x0 < 6 or y1 - y0 < 6 or not self._free(c[None], 4.5)[0]:
                continue
            corners = _rect(c, (1, 0), r.uniform(2.5, 5.5), r.uniform(2.0, 3.5))
            color = np.array([0.55, 0.42, 0.3]) * r.uniform(0.8, 1.25)
            self.boxes.append((corners, -0.2, r.uniform(2.2, 3.0), SHED, color))

    def _lot_clutter(self, lx0, ly0, lw, lh, house):
        r = self.rng
        n = r.integers(1, 4)
        pts = np.column_stack(
            [
                r.uniform(lx0 + 1.5, lx0 + lw - 1.5, n),
                r.uniform(ly0 + 1.5, ly0 + lh - 1.5, n),
            ]
        )
        ok = ~shapely.contains_xy(Polygon(house).buffer(3.5), pts[:, 0], pts[:, 1])
        for p in pts[ok]:
            self._tree(p, small=True)

    def _tree(self, p, small=False):
        r = self.rng
        kind = 1 if r.uniform() < 0.25 else 0
        rad = r.uniform(1.8, 3.2) if small else r.uniform(2.2, 4.5)
        h = r.uniform(5.0, 12.0) if kind == 1 else rad + r.uniform(1.5, 4.0)
        self.trees.append((float(p[0]), float(p[1]), rad, h, kind))

    def street_clutter(self):
        """Parked cars and street trees along every street segment."""
        r = self.rng
        L = self.layout
        for axis in (0, 1):
            lines, widths = (L.xs, L.wx) if axis == 0 else (L.ys, L.wy)
            cross, cw = (L.ys, L.wy) if axis == 0 else (L.xs, L.wx)
            for c0, w in zip(lines, widths, strict=True):
                trees = r.uniform() < self.o.street_tree_fraction
                for k in range(len(cross) - 1):
                    s0 = cross[k] + cw[k] / 2 + 4.0
                    s1 = cross[k + 1] - cw[k + 1] / 2 - 4.0
                    for side in (-1.0, 1.0):
                        off = c0 + side * (w / 2 - SIDEWALK_M - 1.1)
                        s = s0 + r.uniform(0, 4)
                        while s < s1 - 3:
                            if r.uniform() < 0.45:
                                self._car(axis, off, s, r.uniform(4.0, 4.8))
                            s += r.uniform(5.8, 7.5)
                        if trees:
                            off_t = c0 + side * (w / 2 - 1.2)
                            for s in np.arange(
                                s0 + r.uniform(0, 3), s1, r.uniform(8, 12)
                            ):
                                p = (off_t, s) if axis == 0 else (s, off_t)
                                self._tree(np.array(p), small=True)
                    if r.uniform() < 0.5:  # a moving car in a lane
                        s = r.uniform(s0, s1)
                        off = c0 + r.choice([-1.0, 1.0]) * 1.8
                        self._car(axis, off, s, r.uniform(4.0, 4.8))

    def _car(self, axis, off, s, length):
        r = self.rng
        c = np.array([off, s]) if axis == 0 else np.array([s, off])
        ax = (0.0, 1.0) if axis == 0 else (1.0, 0.0)
        ang = np.radians(r.uniform(-2, 2))
        ax = np.array(
            [
                ax[0] * np.cos(ang) - ax[1] * np.sin(ang),
                ax[0] * np.sin(ang) + ax[1] * np.cos(ang),
            ]
        )
        corners = _rect(c, ax, length, r.uniform(1.75, 1.9))
        color = CAR_COLORS[r.integers(len(CAR_COLORS))]
        self.boxes.append((corners, -0.05, r.uniform(1.4, 1.6), CAR, color))


def _roof_boxes(
    rng, buildings: list[Building]
) -> list[tuple[np.ndarray, float, float]]:
    """Small unmapped boxes on large flat roofs: (corners local, z0, z1)."""
    out = []
    for b in buildings:
        if b.roof != "flat" or not b.in_scene or b.footprint.area < 150:
            continue
        inner = b.footprint.buffer(-2.5)
        if inner.is_empty:
            continue
        minx, miny, maxx, maxy = inner.bounds
        for _ in range(int(rng.integers(0, 4))):
            c = rng.uniform([minx, miny], [maxx, maxy])
            ang = rng.uniform(0, np.pi)
            corners = _rect(
                c, (np.cos(ang), np.sin(ang)), rng.uniform(1.5, 5), rng.uniform(1.5, 4)
            )
            if shapely.contains_xy(inner, corners[:, 0], corners[:, 1]).all():
                z0 = b.base_z + b.height_m + RIM_HEIGHT_M - 0.1
                out.append((corners, z0, z0 + rng.uniform(1.2, 3.2)))
    return out


def _base_z(terrain: Terrain, footprint) -> float:
    """Exact minimum of the (piecewise-linear) terrain under a footprint.

    The minimum of a piecewise-linear function over a polygon lies on a vertex
    of the overlay of the polygon and the terrain triangles: polygon vertices,
    crossings of polygon edges with grid lines and cell diagonals, and grid
    nodes inside the polygon.
    """
    s = terrain.spacing
    pts = []
    parts = (
        list(footprint.geoms) if isinstance(footprint, MultiPolygon) else [footprint]
    )
    for p in parts:
        for ring in [p.exterior, *p.interiors]:
            xy = np.asarray(ring.coords)
            A, B = xy[:-1], xy[1:]
            pts.append(A)
            fa = np.column_stack(
                [(A[:, 0] - terrain.x0) / s, (A[:, 1] - terrain.y0) / s]
            )
            fb = np.column_stack(
                [(B[:, 0] - terrain.x0) / s, (B[:, 1] - terrain.y0) / s]
            )
            # Crossings with fx = k, fy = k and fx - fy = k (the cell diagonals).
            for ga, gb in (
                (fa[:, 0], fb[:, 0]),
                (fa[:, 1], fb[:, 1]),
                (fa[:, 0] - fa[:, 1], fb[:, 0] - fb[:, 1]),
            ):
                for e in range(len(A)):
                    lo, hi = sorted((ga[e], gb[e]))
                    ks = np.arange(np.ceil(lo), np.floor(hi) + 1)
                    if len(ks) and hi > lo:
                        t = (ks - ga[e]) / (gb[e] - ga[e])
                        pts.append(A[e] + t[:, None] * (B[e] - A[e]))
        minx, miny, maxx, maxy = p.bounds
        gx = terrain.x0 + s * np.arange(
            np.ceil((minx - terrain.x0) / s), np.floor((maxx - terrain.x0) / s) + 1
        )
        gy = terrain.y0 + s * np.arange(
            np.ceil((miny - terrain.y0) / s), np.floor((maxy - terrain.y0) / s) + 1
        )
        if gx.size and gy.size:
            G = np.stack(np.meshgrid(gx, gy), -1).reshape(-1, 2)
            pts.append(G[shapely.contains_xy(p, G[:, 0], G[:, 1])])
    pts = np.concatenate(pts)
    return float(terrain.height(pts[:, 0], pts[:, 1]).min())


def select_discrepancies(
    options: SceneOptions, seed: int, buildings: list[Building]
) -> None:
    """Mark buildings missing from the map, demolished, or shifted (in place)."""
    rng = stream(seed, STREAM_CADASTRE, 1)
    n = len(buildings)
    order = rng.permutation(n)
    n_missing = int(round(options.cadastre_missing_fraction * n))
    n_demol = int(round(options.cadastre_demolished_fraction * n))
    n_shift = int(round(options.cadastre_shifted_fraction * n))
    for k, i in enumerate(order):
        b = buildings[i]
        if k < n_missing:
            b.in_map = False
        elif k < n_missing + n_demol:
            b.in_scene = False
        elif k < n_missing + n_demol + n_shift:
            ang = rng.uniform(0, 2 * np.pi)
            mag = options.cadastre_shift_m * rng.uniform(0.8, 1.2)
            b.shift_m = (float(mag * np.cos(ang)), float(mag * np.sin(ang)))


def build_city(options: SceneOptions, seed: int) -> City:
    """Build the city of a scene deterministically from ``(options, seed)``.

    Parameters
    ----------
    options : SceneOptions; only the terrain, layout, cadastre and camera
        footprint fields matter (not the image size or priors).
    seed : int

    Returns
    -------
    City, local frame.
    """
    rng = stream(seed, STREAM_CITY)
    extent = city_extent(options)
    terrain = make_terrain(options, stream(seed, STREAM_CITY, 1), extent)
    theta = np.radians(options.grid_rotation_deg)
    xmin, ymin, xmax, ymax = extent
    corners_local = np.array([[xmin, ymin], [xmax, ymin], [xmax, ymax], [xmin, ymax]])
    dummy = Layout(
        theta, np.zeros(1), np.zeros(1), np.zeros(1), np.zeros(1), np.zeros((0, 0))
    )
    cg = dummy.to_grid(corners_local)
    xs, wx = _street_lines(cg[:, 0].min(), cg[:, 0].max(), rng, options)
    ys, wy = _street_lines(cg[:, 1].min(), cg[:, 1].max(), rng, options)
    layout = Layout(theta, xs, wx, ys, wy, np.zeros((len(ys) - 1, len(xs) - 1), int))
    cb = _CityBuilder(options, rng, layout)
    area = Polygon(corners_local).buffer(30.0)
    for ky in range(len(ys) - 1):
        for kx in range(len(xs) - 1):
            x0, x1 = xs[kx] + wx[kx] / 2, xs[kx + 1] - wx[kx + 1] / 2
            y0, y1 = ys[ky] + wy[ky] / 2, ys[ky + 1] - wy[ky + 1] / 2
            blk = Polygon(
                layout.to_local(np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]))
            )
            if not blk.intersects(area):
                layout.block_kind[ky, kx] = 1
                continue
            layout.block_kind[ky, kx] = cb.block(x0, y0, x1, y1, kx, ky)
    cb.street_clutter()
    for b in cb.buildings:
        b.base_z = _base_z(terrain, b.footprint)
    select_discrepancies(options, seed, cb.buildings)
    roof_boxes = _roof_boxes(stream(seed, STREAM_CITY, 2), cb.buildings)
    city = _assemble(options, seed, extent, terrain, layout, cb, roof_boxes)
    logger.debug(
        "city: %d buildings, %d trees, %d boxes, %d triangles",
        len(cb.buildings),
        len(cb.trees),
        len(cb.boxes) + len(roof_boxes),
        len(city.faces),
    )
    return city


def _assemble(
    options, seed, extent, terrain, layout, cb: _CityBuilder, roof_boxes
) -> City:
    mb = _MeshBuilder()
    tv, tf = terrain.mesh()
    s_ground = mb.surface(GROUND, -1, (0, 0, 0), (1, 0, 0), (0, 1, 0), seed=seed)
    mb.triangles(tv[tf], s_ground)
    for b in cb.buildings:
        if b.in_scene:
            _add_building_mesh(mb, b)
    # Trees: crowns (sphere or cone) and trunks, instanced.
    sphere, cone = _unit_sphere(), _unit_cone()
    trunk = _box_tris(_rect((0, 0), (1, 0), 1.0, 1.0), 0.0, 1.0, top=False)
    rng = stream(seed, STREAM_CITY, 3)
    if cb.trees:
        T = np.array(cb.trees)
        loc = layout.to_local(T[:, :2])
        gz = terrain.height(loc[:, 0], loc[:, 1])
        for i in range(len(T)):
            x, y = loc[i]
            rad, h, kind = T[i, 2], T[i, 3], int(T[i, 4])
            green = np.array([0.25, 0.42, 0.16]) * rng.uniform(0.7, 1.25) + rng.uniform(
                -0.04, 0.04, 3
            )
            if kind == 1:
                green = np.array([0.16, 0.3, 0.16]) * rng.uniform(0.8, 1.2)
            st = mb.surface(
                TREE,
                i,
                (x, y, gz[i]),
                (1, 0, 0),
                (0, 0, 1),
                np.clip(green, 0, 1),
                seed=i * 13 + 1,
            )
            sk = mb.surface(
                TRUNK, i, (x, y, gz[i]), (1, 0, 0), (0, 0, 1), (0.3, 0.24, 0.18)
            )
            if kind == 0:
                zc = gz[i] + h
                tris = sphere * np.array([rad, rad, 0.85 * rad]) + np.array([x, y, zc])
                top = zc
            else:
                tris = cone * np.array([rad, rad, h - 1.0]) + np.array(
                    [x, y, gz[i] + 1.0]
                )
                top = gz[i] + 2.0
            mb.triangles(tris, st)
            mb.triangles(
                trunk * np.array([0.35, 0.35, top - gz[i] + 0.3])
                + np.array([x, y, gz[i] - 0.3]),
                sk,
            )
    # Boxes: cars, sheds (grid frame), roof boxes (local).
    box_corners, box_z = [], []
    for i, (corners_g, dz, height, mat, color) in enumerate(cb.boxes):
        c = layout.to_local(corners_g)
        z0 = float(terrain.height(c[:, 0], c[:, 1]).min()) + dz
        s = mb.surface(
            mat,
            i,
            (c[0, 0], c[0, 1], z0),
            (1, 0, 0),
            (0, 0, 1),
            color,
            color * 0.6 if mat == SHED else (0.1, 0.12, 0.15),
            height=height,
            seed=i * 17 + 3,
        )
        mb.triangles(_box_tris(c, z0, z0 + height), s)
        box_corners.append(c)
        box_z.append((z0, z0 + height))
    for j, (c, z0, z1) in enumerate(roof_boxes):
        color = np.array([0.72, 0.72, 0.7]) * rng.uniform(0.75, 1.15)
        s = mb.surface(
            SHED,
            100000 + j,
            (c[0, 0], c[0, 1], z0),
            (1, 0, 0),
            (0, 0, 1),
            color,
            color * 0.8,
            height=z1 - z0,
            seed=j * 19 + 5,
        )
        mb.triangles(_box_tris(c, z0, z1), s)
        box_corners.append(c)
        box_z.append((z0, z1))
    return _city_from_builder(
        mb, options, seed, extent, terrain, layout, cb.buildings, box_corners, box_z
    )


def _city_from_builder(
    mb, options, seed, extent, terrain, layout, buildings, box_corners, box_z
) -> City:
    tris = mb.oriented()
    n = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0])
    norm = np.linalg.norm(n, axis=1)
    keep = norm > 1e-9
    tris, n, norm = tris[keep], n[keep], norm[keep]
    face_surface = np.concatenate(mb.tri_surf)[keep]
    S = mb.surf
    return City(
        options=options,
        seed=seed,
        extent=extent,
        terrain=terrain,
        layout=layout,
        buildings=buildings,
        vertices=tris.reshape(-1, 3),
        faces=np.arange(3 * len(tris), dtype=np.int32).reshape(-1, 3),
        face_normal=n / norm[:, None],
        face_surface=face_surface.astype(np.int32),
        surf_material=np.asarray(S["material"], np.int8),
        surf_object=np.asarray(S["object"], np.int32),
        surf_origin=np.asarray(S["origin"]),
        surf_u=np.asarray(S["u"]),
        surf_v=np.asarray(S["v"]),
        surf_length=np.asarray(S["length"]),
        surf_height=np.asarray(S["height"]),
        surf_color=np.asarray(S["color"], np.float32),
        surf_color2=np.asarray(S["color2"], np.float32),
        surf_style=np.asarray(S["style"]),
        surf_seed=np.asarray(S["seed"], np.uint32),
        boxes=np.asarray(box_corners).reshape(-1, 4, 2),
        box_z=np.asarray(box_z).reshape(-1, 2),
    )


def toy_city(triangles: np.ndarray, colors: np.ndarray, options: SceneOptions) -> City:
    """A "city" of given triangles in flat colours (for tests of the renderer).

    Parameters
    ----------
    triangles : (M, 3, 3) local vertices; the winding defines the front side.
    colors : (M, 3) RGB in [0, 1], rendered exactly (material FLAT).
    """
    mb = _MeshBuilder()
    for tri, col in zip(
        np.asarray(triangles, float), np.asarray(colors, float), strict=True
    ):
        mb.triangles(tri[None], mb.surface(FLAT, color=col, color2=col))
    terrain = Terrain(-1.0, -1.0, 1.0, np.zeros((3, 3)))
    layout = Layout(
        0.0,
        np.array([-1e6, 1e6]),
        np.ones(2),
        np.array([-1e6, 1e6]),
        np.ones(2),
        np.zeros((1, 1), int),
    )
    return _city_from_builder(
        mb, options, 0, (-1.0, -1.0, 1.0, 1.0), terrain, layout, [], [], []
    )


# --------------------------------------------------------------------------
# Ground-truth geometry derived from the buildings
# --------------------------------------------------------------------------


def window_columns(
    length: np.ndarray, style: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Number of window columns and the u of the first column centre, per wall.

    Parameters
    ----------
    length : (N,) wall lengths, m. style : (N, 8) facade styles.

    Returns
    -------
    n_cols : (N,) int; u0 : (N,) float, m (centres at ``u0 + k * col_spacing``).
    """
    win_w, col = style[:, 2], style[:, 5]
    n = np.floor((length - 2 * WINDOW_MARGIN_M - win_w) / np.maximum(col, 1e-6)) + 1
    n = np.where(style[:, 7] > 0, np.maximum(n, 0), 0).astype(int)
    u0 = 0.5 * length - 0.5 * (n - 1) * col
    return n, u0


def window_floors(height: np.ndarray, style: np.ndarray) -> np.ndarray:
    """(N,) number of window floors above the ground floor."""
    floor_h, ground_h = style[:, 0], style[:, 1]
    return np.maximum(
        np.floor((height - ground_h - 0.6) / np.maximum(floor_h, 1e-6)), 0
    ).astype(int)


def corners(city: City) -> dict:
    """True 3D building corners (local frame) of the buildings in the scene.

    For each footprint vertex: the ground point (terrain height at the
    vertex, where the wall meets the terrain) and the eave point (top of the
    wall); ridge ends of pitched roofs. Also per corner two unit horizontal
    directions along the adjacent walls (for visibility sampling).

    Returns
    -------
    dict with ``xyz`` (N, 3), ``building`` (N,), ``kind`` list of str,
    ``dir_a``, ``dir_b`` (N, 2).
    """
    xyz, bid, kind, da, db = [], [], [], [], []
    for b in city.buildings:
        if not b.in_scene:
            continue
        for part in b.parts:
            for ring in _rings(part):
                prev, nxt = np.roll(ring, 1, 0), np.roll(ring, -1, 0)
                a = prev - ring
                a /= np.linalg.norm(a, axis=1, keepdims=True)
                c = nxt - ring
                c /= np.linalg.norm(c, axis=1, keepdims=True)
                g = city.terrain.height(ring[:, 0], ring[:, 1])
                for zs, k in (
                    (g, "ground"),
                    (np.full(len(ring), b.base_z + b.height_m), "eave"),
                ):
                    xyz.append(np.column_stack([ring, zs]))
                    bid += [b.id] * len(ring)
                    kind += [k] * len(ring)
                    da.append(a)
                    db.append(c)
        rp = b.ridge_points()
        if len(rp):
            xyz.append(rp)
            bid += [b.id] * len(rp)
            kind += ["ridge"] * len(rp)
            axis = rp[1, :2] - rp[0, :2]
            n = np.linalg.norm(axis)
            axis = axis / n if n > 0 else np.array([1.0, 0.0])
            da.append(np.stack([axis, -axis]))
            db.append(np.stack([axis, -axis]))
    return {
        "xyz": np.concatenate(xyz) if xyz else np.zeros((0, 3)),
        "building": np.asarray(bid, int),
        "kind": kind,
        "dir_a": np.concatenate(da) if da else np.zeros((0, 2)),
        "dir_b": np.concatenate(db) if db else np.zeros((0, 2)),
    }


def vertical_edges(city: City) -> dict:
    """All true 3D vertical edges of the city (local frame).

    Kinds: 0 "corner" (building corners, terrain to eave), 1 "texture"
    (window frames and shop fronts, from the same layout as the shading), 2
    "clutter" (box corners of sheds, roof boxes and cars).

    Returns
    -------
    dict with ``p0``, ``p1`` (E, 3) bottom and top, ``kind`` (E,) int,
    ``dir_a``, ``dir_b`` (E, 2) horizontal directions into the adjacent faces
    (zero for edges lying inside a face).
    """
    p0, p1, kind, da, db = [], [], [], [], []
    cs = corners(city)
    is_ground = np.array([k == "ground" for k in cs["kind"]], bool)
    is_eave = np.array([k == "eave" for k in cs["kind"]], bool)
    p0.append(cs["xyz"][is_ground])
    p1.append(cs["xyz"][is_eave])
    kind.append(np.zeros(is_ground.sum(), int))
    da.append(cs["dir_a"][is_ground])
    db.append(cs["dir_b"][is_ground])
    # Texture edges of walls with windows.
    wall = (city.surf_material == WALL) & (city.surf_style[:, 7] > 0)
    idx = np.nonzero(wall)[0]
    st = city.surf_style[idx]
    L, H = city.surf_length[idx], city.surf_height[idx]
    n_cols, u0 = window_columns(L, st)
    n_up = window_floors(H, st)
    org, U = city.surf_origin[idx], city.surf_u[idx]
    for w in range(len(idx)):
        floor_h, ground_h, win_w, win_h, sill, col, shop, _ = st[w]
        us = u0[w] + col * np.arange(n_cols[w])
        us = np.concatenate([us - win_w / 2, us + win_w / 2])
        bottoms = ground_h + floor_h * np.arange(n_up[w]) + sill
        if not shop and ground_h >= sill + win_h + 0.3:
            bottoms = np.concatenate([[sill], bottoms])
        if len(us) and len(bottoms):
            U_, B_ = np.meshgrid(us, bottoms)
            base = org[w][None, :2] + U_.ravel()[:, None] * U[w][None, :2]
            z0 = org[w][2] + B_.ravel()
            p0.append(np.column_stack([base, z0]))
            p1.append(np.column_stack([base, z0 + win_h]))
        if shop:
            su = np.concatenate(
                [
                    [WINDOW_MARGIN_M, L[w] - WINDOW_MARGIN_M],
                    u0[w] + col * (np.arange(max(n_cols[w] - 1, 0)) + 0.5) - 0.25,
                    u0[w] + col * (np.arange(max(n_cols[w] - 1, 0)) + 0.5) + 0.25,
                ]
            )
            base = org[w][None, :2] + su[:, None] * U[w][None, :2]
            p0.append(np.column_stack([base, np.full(len(su), org[w][2] + 0.5)]))
            p1.append(
                np.column_stack([base, np.full(len(su), org[w][2] + ground_h - 0.6)])
            )
    n_tex = sum(len(p) for p in p0) - len(kind[0])
    kind.append(np.ones(n_tex, int))
    da.append(np.zeros((n_tex, 2)))
    db.append(np.zeros((n_tex, 2)))
    # Clutter boxes.
    if len(city.boxes):
        c = city.boxes  # (B, 4, 2)
        prev, nxt = np.roll(c, 1, 1), np.roll(c, -1, 1)
        a = (prev - c) / np.linalg.norm(prev - c, axis=2, keepdims=True)
        b = (nxt - c) / np.linalg.norm(nxt - c, axis=2, keepdims=True)
        z0 = np.repeat(city.box_z[:, 0], 4)
        z1 = np.repeat(city.box_z[:, 1], 4)
        p0.append(np.column_stack([c.reshape(-1, 2), z0]))
        p1.append(np.column_stack([c.reshape(-1, 2), z1]))
        kind.append(np.full(len(z0), 2))
        da.append(a.reshape(-1, 2))
        db.append(b.reshape(-1, 2))
    return {
        "p0": np.concatenate(p0),
        "p1": np.concatenate(p1),
        "kind": np.concatenate(kind),
        "dir_a": np.concatenate(da),
        "dir_b": np.concatenate(db),
    }
