"""Tests of obliq_colmap.cadastre: loading, cleaning, corners/edges, visibility."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest
import shapely

from obliq_colmap.cadastre import (
    CadastreOptions,
    load_cadastre,
    normalize_crs,
    visible_corners,
    visible_edge_parts,
    visible_edges,
    write_geojson,
)
from obliq_colmap.errors import InputError
from obliq_colmap.geometry import Camera, Pose, project

DATA = Path(__file__).parent / "data"
SHAPES = DATA / "cadastre_shapes.geojson"
REAL_DIR = Path("/work/shared/data/cityjson_samples/derived_footprints")
ORIGIN = np.array([500_000.0, 5_600_000.0, 0.0])

ANGLE_TOL_DEG = 1e-6
XY_TOL_M = 1e-6


@pytest.fixture(scope="module")
def shapes():
    """rect (20 x 10 m), L (reflex corner), court (hole), multi (2 parts)."""
    return load_cadastre(SHAPES)


def _building(cadastre, building_id: str) -> np.ndarray:
    return np.flatnonzero(cadastre.building_ids == building_id)


def _corners_of(cadastre, building: int) -> np.ndarray:
    return np.flatnonzero(cadastre.corner_building == building)


def _write(path: Path, doc) -> Path:
    path.write_text(doc if isinstance(doc, str) else json.dumps(doc))
    return path


def _square_feature(x0: float, y0: float, size: float = 10.0, **props) -> dict:
    ring = [
        [x0, y0],
        [x0 + size, y0],
        [x0 + size, y0 + size],
        [x0, y0 + size],
        [x0, y0],
    ]
    return {
        "type": "Feature",
        "properties": props,
        "geometry": {"type": "Polygon", "coordinates": [ring]},
    }


def _collection(features, crs="EPSG:25832") -> dict:
    doc = {"type": "FeatureCollection", "features": features}
    if crs is not None:
        doc["crs"] = {"type": "name", "properties": {"name": crs}}
    return doc


# --------------------------------------------------------------------------
# Loading and structure
# --------------------------------------------------------------------------


def test_smoke_shapes(shapes):
    assert shapes.crs == "EPSG:25832"
    np.testing.assert_array_equal(shapes.origin, ORIGIN)
    assert shapes.num_buildings == 5  # the MultiPolygon gives two
    assert list(shapes.building_ids) == ["rect", "L", "court", "multi", "multi"]
    np.testing.assert_array_equal(shapes.feature_index, [0, 1, 2, 3, 3])
    np.testing.assert_array_equal(shapes.heights[:2], [12.0, 9.5])
    assert np.all(np.isnan(shapes.heights[2:]))
    # rect 4 + L 6 + court 4 + 4 + multi 4 + 4
    assert shapes.num_corners == shapes.num_edges == 26
    assert shapes.report.num_features == 4
    assert shapes.report.num_repaired == 0


def test_shapes_of_arrays(shapes):
    C, E, B = shapes.num_corners, shapes.num_edges, shapes.num_buildings
    assert shapes.origin.shape == (3,)
    assert shapes.building_ids.shape == shapes.heights.shape == (B,)
    assert shapes.corner_xy.shape == (C, 2)
    assert shapes.corner_building.shape == shapes.corner_angle_deg.shape == (C,)
    assert shapes.corner_bisector.shape == shapes.corner_edges.shape == (C, 2)
    assert shapes.edge_xy.shape == (E, 2, 2)
    assert shapes.edge_normal.shape == shapes.edge_corners.shape == (E, 2)
    assert shapes.edge_building.shape == shapes.edge_length.shape == (E,)
    assert shapes.edge_shared_fraction.shape == (E,)


def test_local_frame(shapes):
    rect = _building(shapes, "rect")[0]
    xmin, ymin, xmax, ymax = shapes.polygons[rect].bounds
    np.testing.assert_allclose([xmin, ymin, xmax, ymax], [0, 0, 20, 10], atol=XY_TOL_M)
    absolute = shapes.absolute_polygons()[rect]
    np.testing.assert_allclose(
        absolute.bounds, [500_000, 5_600_000, 500_020, 5_600_010]
    )


def test_given_origin():
    cad = load_cadastre(SHAPES, origin=(500_010.0, 5_600_020.0))
    np.testing.assert_array_equal(cad.origin, [500_010.0, 5_600_020.0, 0.0])
    rect = _building(cad, "rect")[0]
    np.testing.assert_allclose(cad.polygons[rect].bounds, [-10, -20, 10, -10])


def test_rectangle_corners(shapes):
    rect = _building(shapes, "rect")[0]
    idx = _corners_of(shapes, rect)
    np.testing.assert_allclose(shapes.corner_angle_deg[idx], 90.0, atol=ANGLE_TOL_DEG)
    np.testing.assert_allclose(np.sort(shapes.edge_length[idx]), [10, 10, 20, 20])
    # Counter-clockwise exterior: positive signed area of the corner sequence.
    xy = shapes.corner_xy[idx]
    area = 0.5 * np.sum(
        xy[:, 0] * np.roll(xy[:, 1], -1) - np.roll(xy[:, 0], -1) * xy[:, 1]
    )
    assert area == pytest.approx(200.0)
    assert not shapes.corner_is_hole[idx].any()


def test_l_shape_has_one_reflex_corner(shapes):
    idx = _corners_of(shapes, _building(shapes, "L")[0])
    angles = np.sort(shapes.corner_angle_deg[idx])
    np.testing.assert_allclose(angles, [90] * 5 + [270], atol=ANGLE_TOL_DEG)
    reflex = idx[np.argmax(shapes.corner_angle_deg[idx])]
    np.testing.assert_allclose(shapes.corner_xy[reflex], [50 - 0, 10], atol=XY_TOL_M)
    # The outward bisector of the reflex corner points into the notch (+x, +y).
    np.testing.assert_allclose(shapes.corner_bisector[reflex], [np.sqrt(0.5)] * 2)


def test_courtyard_hole_corners_are_reflex(shapes):
    court = _building(shapes, "court")[0]
    assert len(shapes.polygons[court].interiors) == 1
    idx = _corners_of(shapes, court)
    hole = idx[shapes.corner_is_hole[idx]]
    outer = idx[~shapes.corner_is_hole[idx]]
    assert len(hole) == len(outer) == 4
    np.testing.assert_allclose(shapes.corner_angle_deg[hole], 270.0, atol=ANGLE_TOL_DEG)
    np.testing.assert_allclose(shapes.corner_angle_deg[outer], 90.0, atol=ANGLE_TOL_DEG)
    # The hole was given counter-clockwise; it is stored clockwise.
    assert not shapes.polygons[court].interiors[0].is_ccw
    assert shapes.polygons[court].exterior.is_ccw


def test_multipolygon_parts(shapes):
    parts = _building(shapes, "multi")
    assert len(parts) == 2
    assert sorted(shapes.polygons[b].area for b in parts) == pytest.approx([100, 100])


def test_bisectors_and_normals_point_outward(shapes):
    polygons = np.asarray(shapes.polygons, dtype=object)
    step_m = 0.01
    out = shapely.points(shapes.corner_xy + step_m * shapes.corner_bisector)
    inside = shapely.points(shapes.corner_xy - step_m * shapes.corner_bisector)
    owner = polygons[shapes.corner_building]
    assert not shapely.contains(owner, out).any()
    assert shapely.contains(owner, inside).all()
    np.testing.assert_allclose(np.linalg.norm(shapes.corner_bisector, axis=1), 1.0)

    mid = shapes.edge_xy.mean(axis=1)
    owner = polygons[shapes.edge_building]
    assert not shapely.contains(
        owner, shapely.points(mid + step_m * shapes.edge_normal)
    ).any()
    assert shapely.contains(
        owner, shapely.points(mid - step_m * shapes.edge_normal)
    ).all()


def test_corner_edge_topology(shapes):
    # Edge k starts at corner k; a corner's incoming edge ends at it.
    np.testing.assert_array_equal(
        shapes.corner_edges[:, 1], np.arange(shapes.num_corners)
    )
    np.testing.assert_array_equal(
        shapes.edge_corners[shapes.corner_edges[:, 0], 1], np.arange(shapes.num_corners)
    )
    np.testing.assert_allclose(shapes.edge_xy[:, 0], shapes.corner_xy)
    np.testing.assert_allclose(
        shapes.edge_xy[:, 1], shapes.corner_xy[shapes.edge_corners[:, 1]]
    )
    np.testing.assert_array_equal(shapes.edge_building, shapes.corner_building)


def test_duplicate_collinear_and_cw_input_cleaned():
    cad = load_cadastre(DATA / "cadastre_dirty.geojson")
    assert cad.crs == "EPSG:25832"
    assert cad.num_buildings == 1 and cad.num_corners == 4
    assert cad.polygons[0].exterior.is_ccw  # given clockwise
    np.testing.assert_allclose(cad.corner_angle_deg, 90.0, atol=1.0)
    np.testing.assert_allclose(cad.polygons[0].bounds, [0, 0, 20, 10], atol=0.02)
    assert cad.report.num_repaired == 0
    assert cad.report.num_vertices_removed == 4


def test_collinear_offset_guard_keeps_bent_facade(tmp_path):
    # A 2 deg bend between two 30 m walls: 0.52 m off the chord.
    bend = 30 * np.tan(np.radians(1.0))
    ring = [[0, 0], [30, -bend], [60, 0], [60, 20], [0, 20], [0, 0]]
    feature = {
        "type": "Feature",
        "properties": {},
        "geometry": {
            "type": "Polygon",
            "coordinates": [[[500_000 + x, 5_600_000 + y] for x, y in ring]],
        },
    }
    path = _write(tmp_path / "bent.geojson", _collection([feature]))
    assert load_cadastre(path).num_corners == 5
    loose = CadastreOptions(collinear_max_offset_m=np.inf)
    assert load_cadastre(path, loose).num_corners == 4


def test_bowtie_repaired():
    cad = load_cadastre(DATA / "cadastre_bowtie.geojson")
    bow = _building(cad, "bow")
    assert len(bow) == 2  # two triangles
    np.testing.assert_allclose([cad.polygons[b].area for b in bow], [25, 25])
    assert all(cad.polygons[b].is_valid for b in bow)
    assert cad.report.num_repaired == 1


def test_bowtie_rejected_without_repair():
    path = DATA / "cadastre_bowtie.geojson"
    with pytest.raises(InputError, match=r"feature 1 \(id 'bow'\).*invalid") as info:
        load_cadastre(path, CadastreOptions(repair_invalid=False))
    assert info.value.path == path


def test_touching_parts_dissolved(tmp_path):
    # One building stored as two ground polygons sharing a wall (invalid as a
    # MultiPolygon): repaired into one footprint without the interior wall.
    coords = [
        [
            [
                [500_000, 5_600_000],
                [500_010, 5_600_000],
                [500_010, 5_600_010],
                [500_000, 5_600_010],
                [500_000, 5_600_000],
            ]
        ],
        [
            [
                [500_010, 5_600_000],
                [500_020, 5_600_000],
                [500_020, 5_600_010],
                [500_010, 5_600_010],
                [500_010, 5_600_000],
            ]
        ],
    ]
    feature = {
        "type": "Feature",
        "properties": {"id": "b"},
        "geometry": {"type": "MultiPolygon", "coordinates": coords},
    }
    cad = load_cadastre(_write(tmp_path / "parts.geojson", _collection([feature])))
    assert cad.num_buildings == 1 and cad.num_corners == 4
    assert cad.polygons[0].area == pytest.approx(200.0)


def test_ids_heights_and_party_walls():
    cad = load_cadastre(DATA / "cadastre_row.geojson")
    assert list(cad.building_ids) == ["17", "1"]  # GeoJSON id, then the index
    np.testing.assert_array_equal(cad.heights[:1], [8.0])
    assert np.isnan(cad.heights[1])
    # Local x spans 0..20; the party wall is at x = 10 (once per house).
    shared = np.all(np.isclose(cad.edge_xy[:, :, 0], 10.0), axis=1)
    np.testing.assert_allclose(cad.edge_shared_fraction[shared], 1.0)
    np.testing.assert_allclose(cad.edge_shared_fraction[~shared], 0.0)
    assert shared.sum() == 2


def test_small_and_empty_polygons_dropped(tmp_path, caplog):
    empty = {
        "type": "Feature",
        "properties": {"id": "gone"},
        "geometry": {"type": "Polygon", "coordinates": []},
    }
    point = {
        "type": "Feature",
        "properties": {},
        "geometry": {"type": "Point", "coordinates": [500_000, 5_600_000]},
    }
    tiny = _square_feature(500_050, 5_600_000, size=0.5, id="tiny")
    doc = _collection([_square_feature(500_000, 5_600_000, id="a"), empty, point, tiny])
    with caplog.at_level(logging.WARNING, logger="obliq_colmap.cadastre"):
        cad = load_cadastre(_write(tmp_path / "m.geojson", doc))
    assert list(cad.building_ids) == ["a"]
    assert cad.report.num_skipped == 3
    text = caplog.text
    # one line for the features that are not footprints, naming them
    assert "skipped 2 of 4 features" in text
    assert "1 with an empty Polygon (features 1)" in text
    assert "1 with geometry type 'Point' (features 2)" in text
    assert "feature 3 (id 'tiny')" in text


def test_a_map_of_lines_is_one_error_not_a_warning_per_feature(tmp_path, caplog):
    lines = [
        {
            "type": "Feature",
            "properties": {},
            "geometry": {
                "type": "LineString",
                "coordinates": [[500_000 + i, 5_600_000], [500_010 + i, 5_600_000]],
            },
        }
        for i in range(50)
    ]
    path = _write(tmp_path / "lines.geojson", _collection(lines))
    with (
        caplog.at_level(logging.WARNING, logger="obliq_colmap.cadastre"),
        pytest.raises(InputError, match="50 with geometry type 'LineString'"),
    ):
        load_cadastre(path)
    assert caplog.text == ""


def test_buildings_near_and_in_box(shapes):
    rect = _building(shapes, "rect")[0]
    L = _building(shapes, "L")[0]
    np.testing.assert_array_equal(shapes.buildings_near((10, 5)), [rect])
    np.testing.assert_array_equal(
        shapes.buildings_near((30, 5), radius_m=10.5), [rect, L]
    )
    assert len(shapes.buildings_near((30, 5), radius_m=5)) == 0
    np.testing.assert_array_equal(shapes.buildings_in_box(15, -5, 45, 5), [rect, L])


def test_write_geojson_round_trip(shapes, tmp_path):
    props = [
        {"id": str(i), "height": float(h) if np.isfinite(h) else None}
        for i, h in zip(shapes.building_ids, shapes.heights, strict=True)
    ]
    path = write_geojson(
        tmp_path / "out.geojson", shapes.absolute_polygons(), shapes.crs, props
    )
    again = load_cadastre(path)
    assert again.crs == shapes.crs
    np.testing.assert_array_equal(again.origin, shapes.origin)
    np.testing.assert_allclose(again.corner_xy, shapes.corner_xy, atol=1e-3)
    np.testing.assert_array_equal(again.building_ids, shapes.building_ids)
    np.testing.assert_array_equal(again.heights, shapes.heights)


@pytest.mark.parametrize(
    ("name", "expected"),
    [
        ("urn:ogc:def:crs:EPSG::28992", "EPSG:28992"),
        ("EPSG:25832", "EPSG:25832"),
        ("http://www.opengis.net/def/crs/EPSG/0/2056", "EPSG:2056"),
        ("urn:ogc:def:crs:OGC:1.3:CRS84", "OGC:CRS84"),
        ("LOCAL_CS", "LOCAL_CS"),
    ],
)
def test_normalize_crs(name, expected):
    assert normalize_crs(name) == expected


# --------------------------------------------------------------------------
# Bad input
# --------------------------------------------------------------------------


def test_rfc7946_lonlat_is_reprojected_into_its_utm_zone():
    """RFC 7946 GeoJSON (no crs member, WGS 84 longitude / latitude): a
    footprint in Delft goes into UTM 31N; its sides, by hand: 0.0003 deg of
    longitude at 52.0117 N is 111,320 m x cos(lat) x 0.0003 = 20.56 m,
    0.0002 deg of latitude 22.26 m (UTM's scale there ~0.9997)."""
    pytest.importorskip("pyproj")
    cad = load_cadastre(DATA / "cadastre_lonlat.geojson")
    assert cad.crs == "EPSG:32631"
    area = cad.polygons[0].area
    expected = 111_320 * math.cos(math.radians(52.0117)) * 0.0003 * 22.26
    assert area == pytest.approx(expected, rel=0.005)


def test_a_map_is_brought_into_the_crs_asked_for():
    pytest.importorskip("pyproj")
    utm = load_cadastre(DATA / "cadastre_lonlat.geojson")
    again = load_cadastre(
        DATA / "cadastre_lonlat.geojson", CadastreOptions(crs="EPSG:25831")
    )
    assert again.crs == "EPSG:25831"  # ETRS89 / UTM 31N: the same grid to cm
    np.testing.assert_allclose(
        again.corner_xy + again.origin[:2], utm.corner_xy + utm.origin[:2], atol=0.02
    )


def test_a_lonlat_crs_member_with_projected_coordinates_is_refused(tmp_path):
    doc = _collection(
        [_square_feature(500_000, 5_600_000)], crs="urn:ogc:def:crs:OGC:1.3:CRS84"
    )
    with pytest.raises(InputError, match="longitude/latitude but its coordinates"):
        load_cadastre(_write(tmp_path / "crs84.geojson", doc))


def test_small_local_coordinates_are_kept_local_on_request(tmp_path):
    pytest.importorskip("pyproj")
    path = _write(
        tmp_path / "local.geojson", _collection([_square_feature(0, 0)], None)
    )
    # RFC 7946: without a crs member these are degrees, and are reprojected
    assert load_cadastre(path).crs == "EPSG:32631"
    cad = load_cadastre(path, CadastreOptions(allow_degree_range=True))
    assert cad.num_corners == 4 and cad.crs is None


def test_a_geopackage_map_reads_as_its_geojson(tmp_path):
    pyogrio = pytest.importorskip("pyogrio")
    src = DATA / "cadastre_shapes.geojson"
    gpkg = tmp_path / "shapes.gpkg"
    meta, _, wkb, fields = pyogrio.raw.read(src)
    pyogrio.raw.write(
        gpkg,
        wkb,
        fields,
        meta["fields"],
        geometry_type=meta["geometry_type"],
        crs=meta["crs"],
        driver="GPKG",
    )
    a, b = load_cadastre(src), load_cadastre(gpkg)
    assert list(a.building_ids) == list(b.building_ids) and a.crs == b.crs
    np.testing.assert_allclose(a.corner_xy, b.corner_xy)


@pytest.mark.parametrize(
    ("content", "message"),
    [
        ("{not json", "not valid JSON"),
        (
            json.dumps({"type": "Feature", "geometry": None}),
            "not a GeoJSON FeatureCollection",
        ),
        (json.dumps([1, 2]), "not a GeoJSON FeatureCollection"),
        (json.dumps({"type": "FeatureCollection", "features": []}), "no Polygon"),
        (
            json.dumps(
                _collection(
                    [
                        {
                            "type": "Feature",
                            "properties": {},
                            "geometry": {
                                "type": "LineString",
                                "coordinates": [[0, 0], [1, 1]],
                            },
                        }
                    ]
                )
            ),
            "no Polygon",
        ),
    ],
)
def test_bad_files(tmp_path, content, message):
    path = _write(tmp_path / "bad.geojson", content)
    with pytest.raises(InputError, match=message) as info:
        load_cadastre(path)
    assert info.value.path == path
    assert str(path) in str(info.value)


def test_missing_file(tmp_path):
    path = tmp_path / "nope.geojson"
    with pytest.raises(InputError, match="does not exist") as info:
        load_cadastre(path)
    assert str(path) in str(info.value)


def test_malformed_coordinates_name_the_feature(tmp_path):
    bad = {
        "type": "Feature",
        "properties": {"id": "x7"},
        "geometry": {"type": "Polygon", "coordinates": [[[0, 0], [1, 1]]]},
    }
    doc = _collection([_square_feature(500_000, 5_600_000), bad])
    with pytest.raises(InputError, match=r"feature 1 \(id 'x7'\)"):
        load_cadastre(_write(tmp_path / "m.geojson", doc))


def test_options_validated():
    with pytest.raises(ValueError, match="min_area_m2"):
        CadastreOptions(min_area_m2=-1)
    with pytest.raises(TypeError):
        CadastreOptions(0.05)  # keyword-only


# --------------------------------------------------------------------------
# Visibility
# --------------------------------------------------------------------------


def _camera(focal_px: float = 1000.0, width: int = 2000, height: int = 1500) -> Camera:
    return Camera("PINHOLE", width, height, [focal_px, focal_px, width / 2, height / 2])


def _looking_north(center, tilt_deg: float = 45.0, heading_deg: float = 0.0) -> Pose:
    """Camera at ``center`` looking along a heading (0 north, 90 east), tilted down."""
    h, t = np.radians(heading_deg), np.radians(tilt_deg)
    forward = np.array([np.sin(h) * np.cos(t), np.cos(h) * np.cos(t), -np.sin(t)])
    right = np.array([np.cos(h), -np.sin(h), 0.0])
    down = np.cross(forward, right)
    return Pose.from_center(np.stack([right, down, forward]), center)


def test_camera_looking_north_sees_south_walls(shapes):
    rect = _building(shapes, "rect")[0]
    pose = _looking_north([10.0, -60.0, 60.0])  # centre of view at (10, 0, 0)
    camera = _camera(focal_px=6000.0)  # narrow: only "rect" is in view

    edges = visible_edges(shapes, camera, pose, 0.0)
    np.testing.assert_array_equal(shapes.edge_building[edges], [rect])
    np.testing.assert_allclose(shapes.edge_normal[edges], [[0.0, -1.0]], atol=1e-12)

    corners = visible_corners(shapes, camera, pose, 0.0)
    np.testing.assert_allclose(np.sort(shapes.corner_xy[corners][:, 0]), [0, 20])
    np.testing.assert_allclose(shapes.corner_xy[corners][:, 1], [0, 0])

    # A wide camera sees more walls (the L's south and west walls), but never
    # a north-facing one (including the courtyard's inner wall at y = 50).
    wide = _camera(focal_px=600.0)
    edges = visible_edges(shapes, wide, pose, 0.0)
    assert set(shapes.building_ids[shapes.edge_building[edges]]) >= {"rect", "L"}
    assert np.all(shapes.edge_normal[edges] @ np.array([0.0, 1.0]) < 0.5)
    north_facing = np.flatnonzero(shapes.edge_normal @ np.array([0.0, 1.0]) > 0.5)
    assert len(north_facing) == 7  # rect 1, L 2, court 1 + hole 1, multi 2
    assert not np.isin(north_facing, edges).any()


def test_corners_outside_frustum_excluded(shapes):
    pose = _looking_north([10.0, -60.0, 60.0])
    camera = _camera(focal_px=6000.0)
    corners = visible_corners(shapes, camera, pose, 0.0)
    rect = _building(shapes, "rect")[0]
    np.testing.assert_array_equal(shapes.corner_building[corners], [rect, rect])
    # The L's west wall faces the camera, but the corners are out of view.
    L_west = np.flatnonzero(
        (shapes.edge_building == _building(shapes, "L")[0])
        & (shapes.edge_normal[:, 0] < -0.5)
    )
    assert len(L_west) == 1
    assert len(visible_corners(shapes, _camera(focal_px=600.0), pose, 0.0)) > 2
    # Looking away (south) from the same place: nothing.
    away = _looking_north([10.0, -60.0, 60.0], heading_deg=180.0)
    assert len(visible_corners(shapes, camera, away, 0.0)) == 0
    assert len(visible_edges(shapes, camera, away, 0.0)) == 0
    # The ground far above the camera: nothing in view either.
    assert len(visible_corners(shapes, camera, pose, 500.0)) == 0


def test_margin_grows_the_view(shapes):
    pose = _looking_north([10.0, -60.0, 60.0])
    camera = _camera(focal_px=6000.0)
    near = visible_corners(shapes, camera, pose, 0.0)
    grown = visible_corners(shapes, camera, pose, 0.0, margin_px=3000)
    assert set(near) < set(grown)


def test_ground_height_function(shapes):
    pose = _looking_north([10.0, -60.0, 60.0])
    camera = _camera(focal_px=600.0)
    constant = visible_corners(shapes, camera, pose, 3.0)
    planar = visible_corners(shapes, camera, pose, lambda xy: 3.0 + 0.0 * xy[:, 0])
    np.testing.assert_array_equal(constant, planar)
    with pytest.raises(ValueError, match="must return shape"):
        visible_corners(shapes, camera, pose, lambda xy: np.zeros(3))


def test_party_walls_not_visible():
    cad = load_cadastre(DATA / "cadastre_row.geojson")
    # From the east, looking west: the party wall (x = 10, local) faces the
    # camera for the western house but is inside the row; only the eastern
    # house's east wall (x = 20) is a facade.
    pose = _looking_north([80.0, 5.0, 40.0], tilt_deg=30.0, heading_deg=270.0)
    edges = visible_edges(cad, _camera(), pose, 0.0)
    np.testing.assert_allclose(cad.edge_xy[edges][:, :, 0], 20.0)
    with_shared = visible_edges(cad, _camera(), pose, 0.0, exclude_shared_walls=False)
    assert len(with_shared) == 2


def _brute_force_corners(cad, camera, pose, ground, h_range, margin_px, samples=801):
    """Reference: sample each facing corner's vertical segment and project."""
    center = pose.center
    facing = np.sum(cad.edge_normal * (center[:2] - cad.edge_xy[:, 0]), axis=1) > 0
    facing &= cad.edge_shared_fraction < 0.9
    t = np.linspace(0.0, 1.0, samples)
    seen = []
    for k in range(cad.num_corners):
        if not facing[cad.corner_edges[k]].any():
            continue
        top = h_range[1]
        h = cad.heights[cad.corner_building[k]]
        if np.isfinite(h):
            top = np.clip(h, *h_range)
        z = ground + h_range[0] + t * (top - h_range[0])
        pts = np.column_stack([np.repeat(cad.corner_xy[k][None], samples, 0), z])
        px, depth = project(camera, pose, pts)
        ok = (
            (depth >= 0.1)
            & (px[:, 0] >= -margin_px)
            & (px[:, 0] <= camera.width + margin_px)
            & (px[:, 1] >= -margin_px)
            & (px[:, 1] <= camera.height + margin_px)
        )
        if ok.any():
            seen.append(k)
    return set(seen)


def _brute_force_edges(cad, camera, pose, ground, h_range, margin_px, samples=121):
    center = pose.center
    facing = np.sum(cad.edge_normal * (center[:2] - cad.edge_xy[:, 0]), axis=1) > 0
    facing &= cad.edge_shared_fraction < 0.9
    s, t = np.meshgrid(np.linspace(0, 1, samples), np.linspace(0, 1, samples))
    s, t = s.ravel(), t.ravel()
    seen = {}
    for e in np.flatnonzero(facing):
        top = h_range[1]
        h = cad.heights[cad.edge_building[e]]
        if np.isfinite(h):
            top = np.clip(h, *h_range)
        p0, p1 = cad.edge_xy[e]
        xy = p0 + s[:, None] * (p1 - p0)
        pts = np.column_stack([xy, ground + h_range[0] + t * (top - h_range[0])])
        px, depth = project(camera, pose, pts)
        ok = (
            (depth >= 0.1)
            & (px[:, 0] >= -margin_px)
            & (px[:, 0] <= camera.width + margin_px)
            & (px[:, 1] >= -margin_px)
            & (px[:, 1] <= camera.height + margin_px)
        )
        if ok.any():
            seen[e] = (s[ok].min(), s[ok].max())
    return seen


def test_visibility_matches_brute_force(shapes):
    """Exact clipping vs dense sampling, two-sided, for random poses."""
    rng = np.random.default_rng(3)
    camera = _camera(focal_px=1500.0)
    h_range = (0.0, 30.0)
    for _ in range(12):
        center = np.array(
            [rng.uniform(-60, 120), rng.uniform(-60, 120), rng.uniform(20, 90)]
        )
        target = np.array([rng.uniform(0, 60), rng.uniform(0, 70)])
        d = target - center[:2]
        heading = np.degrees(np.arctan2(d[0], d[1]))
        pose = _looking_north(center, tilt_deg=rng.uniform(25, 60), heading_deg=heading)
        exact = set(visible_corners(shapes, camera, pose, 1.5, h_range).tolist())
        assert _brute_force_corners(shapes, camera, pose, 1.5, h_range, 0.0) <= exact
        assert exact <= _brute_force_corners(shapes, camera, pose, 1.5, h_range, 5.0)

        idx, clipped = visible_edge_parts(shapes, camera, pose, 1.5, h_range)
        np.testing.assert_array_equal(
            idx, visible_edges(shapes, camera, pose, 1.5, h_range)
        )
        sampled = _brute_force_edges(shapes, camera, pose, 1.5, h_range, 0.0)
        assert set(sampled) <= set(idx.tolist())
        assert set(idx.tolist()) <= set(
            _brute_force_edges(shapes, camera, pose, 1.5, h_range, 5.0)
        )
        # The clipped part contains every sampled visible point of the edge.
        for k, e in enumerate(idx):
            if e not in sampled:
                continue
            p0, p1 = shapes.edge_xy[e]
            length = np.linalg.norm(p1 - p0)
            s0 = np.dot(clipped[k, 0] - p0, p1 - p0) / length**2
            s1 = np.dot(clipped[k, 1] - p0, p1 - p0) / length**2
            assert s0 <= sampled[e][0] + 1e-9 and s1 >= sampled[e][1] - 1e-9
            # ... and is not much longer than the sampled part (grid step 1/120).
            assert s0 >= sampled[e][0] - 1 / 60 and s1 <= sampled[e][1] + 1 / 60


def test_distorted_camera_is_conservative(shapes):
    pose = _looking_north([10.0, -60.0, 60.0])
    pinhole = _camera(focal_px=1000.0)
    distorted = Camera("OPENCV", 2000, 1500, [1000, 1000, 1000, 750, -0.05, 0.01, 0, 0])
    a = set(visible_corners(shapes, pinhole, pose, 0.0).tolist())
    b = set(visible_corners(shapes, distorted, pose, 0.0).tolist())
    # Barrel distortion widens the view: everything the pinhole sees is kept.
    assert a <= b


# --------------------------------------------------------------------------
# Real footprints
# --------------------------------------------------------------------------

REAL_FILE = REAL_DIR / "rotterdam_delfshaven_footprints.geojson"


@pytest.mark.skipif(
    not REAL_FILE.exists(), reason=f"real footprints absent: {REAL_FILE}"
)
def test_real_footprints_delfshaven():
    cad = load_cadastre(REAL_FILE)
    assert cad.crs == "EPSG:28992"
    assert cad.report.num_features == 853
    assert 800 <= cad.num_buildings <= 900
    assert 4 * cad.num_buildings <= cad.num_corners <= 12 * cad.num_buildings
    assert np.all((cad.corner_angle_deg > 0) & (cad.corner_angle_deg < 360))
    assert np.all(cad.edge_length >= CadastreOptions().min_edge_length_m)
    assert all(p.is_valid and p.exterior.is_ccw for p in cad.polygons)
    # The local frame keeps coordinates small (float32-safe).
    assert np.abs(cad.corner_xy).max() < 2000
    # Bisectors point outward on real data too.
    polygons = np.asarray(cad.polygons, dtype=object)[cad.corner_building]
    sharp = (cad.corner_angle_deg > 20) & (cad.corner_angle_deg < 340)
    out = shapely.points(cad.corner_xy + 0.005 * cad.corner_bisector)
    assert not shapely.contains(polygons[sharp], out[sharp]).any()
    # Party walls exist in this dense neighbourhood.
    assert np.mean(cad.edge_shared_fraction > 0.9) > 0.1
    # An oblique camera over the centre sees a sane subset.
    pose = _looking_north([0.0, -250.0, 250.0])
    corners = visible_corners(cad, _camera(), pose, 0.0)
    edges = visible_edges(cad, _camera(), pose, 0.0)
    assert 50 < len(corners) < cad.num_corners / 2
    assert 50 < len(edges) < cad.num_edges / 2


@pytest.mark.parametrize("margin_px", [0.0, 300.0])
def test_the_view_box_keeps_every_corner_the_whole_map_test_finds(margin_px):
    """With a constant ground the corners are first narrowed to the buildings
    the spatial index finds in the frustum's footprint; the result is the
    whole-map test's (a callable ground skips the narrowing) for every
    camera of the sample's priors."""
    from obliq_colmap.cadastre.visibility import _view_box
    from obliq_colmap.colmap_io import read_model

    sample = Path(__file__).resolve().parents[1] / "data_samples" / "oblique_small"
    cad = load_cadastre(sample / "cadastre.geojson")
    priors = read_model(sample / "priors")
    heights = [im.cam_from_world.center[2] for im in priors.images.values()]
    ground = float(np.median(heights)) - 600.0
    for im in priors.images.values():
        camera = priors.cameras[im.camera_id]
        pose = Pose(
            im.cam_from_world.rotation,
            im.cam_from_world.translation + im.cam_from_world.rotation @ cad.origin,
        )
        box = _view_box(camera, pose, (ground, ground + 50.0), margin_px)
        assert box is not None  # the narrowing is what is tested
        fast = visible_corners(cad, camera, pose, ground, (0.0, 50.0), margin_px)
        whole = visible_corners(
            cad,
            camera,
            pose,
            lambda xy: np.full(len(xy), ground),
            (0.0, 50.0),
            margin_px,
        )
        assert len(whole) > 0
        np.testing.assert_array_equal(fast, whole)


def test_area_keeps_the_block_part_of_a_city_map(tmp_path):
    """A city-wide map: only the footprints near the block are cleaned."""
    near = [_square_feature(500_000 + 20 * k, 5_600_000) for k in range(5)]
    far = [_square_feature(520_000 + 20 * k, 5_620_000) for k in range(50)]
    path = _write(tmp_path / "city.geojson", _collection(near + far))
    whole = load_cadastre(path)
    assert whole.num_buildings == 55
    area = (499_900.0, 5_599_900.0, 500_200.0, 5_600_100.0)
    cad = load_cadastre(path, CadastreOptions(area=area))
    assert cad.num_buildings == 5
    assert cad.report.num_features == 55  # the file's count stays in the report
    with pytest.raises(InputError, match="another CRS"):
        load_cadastre(path, CadastreOptions(area=(0.0, 0.0, 100.0, 100.0)))
