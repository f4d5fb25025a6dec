"""Building footprints: GeoJSON -> cleaned polygons, corners and edges in a local frame.

The cadastre stage (paper 000, section 2.2) turns a 2D footprint map into the
plain arrays the registration stages need:

- corners: the map vertices whose vertical edges are matched to vertical image
  lines (eq. 2), with their interior angle and outward bisector;
- edges: the facade walls whose horizontal edges are matched in section 2.3,
  with their outward normal;
- per-camera visibility queries (:func:`visible_corners`,
  :func:`visible_edges`, :func:`visible_edge_parts`) that pick the corners and
  walls a rough pose can see, all vectorised over the whole map.

Entry: :func:`load_cadastre` (path, :class:`CadastreOptions`, optional origin)
-> :class:`Cadastre`.

Data in (see docs/DESIGN.md): a GeoJSON FeatureCollection of Polygon /
MultiPolygon footprints (holes allowed) in a projected metric CRS, an optional
``"crs"`` member and optional ``id`` / ``height`` properties. Longitude /
latitude input is rejected: reprojection is not supported yet.

Data out: a :class:`Cadastre` in a LOCAL metric frame (metres, x east,
y north, ``world_abs = local + origin``, origin (3,)): B cleaned polygons,
(C, 2) corner positions with their angle (degrees), outward bisector and
edges, (E, 2, 2) edge end points with outward normal, length (m) and party
wall fraction, and an STRtree over the polygons. The visibility queries take
a :class:`~obliq_colmap.geometry.Camera` and a ``cam_from_world``
:class:`~obliq_colmap.geometry.Pose` in that local frame and return ascending
(K,) corner or edge indices (and, for :func:`visible_edge_parts`, the (K, 2, 2)
visible part of each edge). :func:`write_geojson` writes footprints in
absolute coordinates back to a file.

Steps of :func:`load_cadastre`:

1. Read and check the JSON document; parse each feature into shapely
   geometries (absolute coordinates); reject degree coordinates.
2. Choose the local origin (rounded centre of the bounds) and translate; all
   arrays of a :class:`Cadastre` are in this LOCAL frame,
   ``world_abs = local + origin``.
3. Validate each feature; repair invalid ones with ``shapely.make_valid``
   (keeping the polygonal parts) or reject them; dissolve the parts of one
   feature that touch (a building stored as several ground polygons).
4. Orient every polygon (exterior counter-clockwise, holes clockwise, so the
   building is always on the LEFT of a ring), drop duplicate / near-duplicate
   vertices and vertices on straight runs, drop tiny polygons and holes.
5. Build the corner and edge arrays (holes are rings of their own: courtyard
   corners are corners too), flag party walls shared with a neighbouring
   building, and build an STRtree over the polygons.

Visibility is a purely geometric test (frustum and back-face culling); it does
NOT model occlusion by other buildings. Later stages handle occlusion through
their robust matching (RANSAC inliers, facade-edge consistency across images).

Modules, in reading order:

- ``options``: :class:`CadastreOptions` (reading and cleaning) and
  :class:`CadastreReport` (counts of one load).
- ``model``: the :class:`Cadastre` dataclass and ``SHARED_WALL_FRACTION``.
- ``read``: steps 1-2, JSON checks, CRS names (:func:`normalize_crs`),
  feature parsing, the metric check and the local origin.
- ``clean``: steps 3-5, repair / dissolve, ring cleaning, turn angles,
  corners and edges, party walls.
- ``load``: :func:`load_cadastre`, the five steps in order; split as
  :func:`read_footprints` (step 1) and :func:`build_cadastre` (steps 2-5,
  keeping only ``CadastreOptions.area``) for callers that need the map's
  CRS before they know the area (``register``: the priors).
- ``visibility``: frustum, facing walls, :func:`visible_corners`,
  :func:`visible_edge_parts`, :func:`visible_edges`, the wall clipping.
- ``write``: :func:`write_geojson`.
"""

from .load import Footprints, build_cadastre, load_cadastre, read_footprints
from .model import SHARED_WALL_FRACTION, Cadastre
from .options import CadastreOptions, CadastreReport
from .read import GEOGRAPHIC_CRS, normalize_crs
from .visibility import (
    GroundHeight,
    visible_corners,
    visible_edge_parts,
    visible_edges,
)
from .write import write_geojson

__all__ = [
    "GEOGRAPHIC_CRS",
    "SHARED_WALL_FRACTION",
    "Cadastre",
    "CadastreOptions",
    "CadastreReport",
    "GroundHeight",
    "Footprints",
    "build_cadastre",
    "load_cadastre",
    "read_footprints",
    "normalize_crs",
    "visible_corners",
    "visible_edge_parts",
    "visible_edges",
    "write_geojson",
]
