"""The stage's entry: :func:`load_cadastre`, GeoJSON file -> :class:`Cadastre`."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import shapely
from shapely.geometry import Polygon

from obliq_colmap.errors import InputError

from .clean import assemble, clean_polygon, valid_parts
from .formats import read_document, to_projected
from .model import SHARED_WALL_FRACTION, Cadastre
from .options import CadastreOptions, CadastreReport
from .read import (
    Feature,
    check_metric,
    choose_origin,
    parse_crs,
    parse_feature,
)

logger = logging.getLogger(__name__)


@dataclass
class Footprints:
    """The map's features, parsed and in a projected CRS (steps 1 of
    :func:`load_cadastre`), before cleaning."""

    path: Path
    crs: str | None
    features: list[Feature]
    report: CadastreReport
    t_start: float


def load_cadastre(
    path: str | Path,
    options: CadastreOptions | None = None,
    origin: Sequence[float] | np.ndarray | None = None,
) -> Cadastre:
    """Read a GeoJSON footprint map into a :class:`Cadastre` in a local frame.

    Parameters
    ----------
    path : str or Path
        GeoJSON FeatureCollection of Polygon / MultiPolygon features in a
        projected metric CRS (or Shapefile / GeoPackage, or RFC 7946
        longitude / latitude, reprojected). Other geometry types and null
        geometries are skipped with a warning.
    options : CadastreOptions, optional
        Cleaning options; the defaults suit 1 cm to 10 cm cadastral maps.
        ``options.area`` keeps only the features within those bounds.
    origin : (2,) or (3,) array-like, optional
        Absolute coordinates (m) of the local origin, e.g. to share a frame
        with a priors model. Default: the centre of the kept features'
        bounds rounded to ``options.origin_rounding_m``, with z = 0.

    Returns
    -------
    Cadastre
        Everything in the local frame, ``world_abs = local + origin``.

    Raises
    ------
    InputError
        Naming the file (and the feature's index and id where one is at fault):
        missing or unreadable file, not JSON, not a FeatureCollection, no
        polygon features, malformed coordinates, invalid geometry that cannot
        be repaired (or ``repair_invalid`` is False), coordinates in degrees,
        no feature within ``options.area``.
    """
    options = CadastreOptions() if options is None else options
    return build_cadastre(read_footprints(path, options), options, origin)


def read_footprints(path: str | Path, options: CadastreOptions) -> Footprints:
    """Step 1 of :func:`load_cadastre`: parse the features, reproject them."""
    t_start = time.perf_counter()
    path = Path(path)
    doc = read_document(path)
    crs = parse_crs(path, doc.get("crs"))
    report = CadastreReport(num_features=len(doc["features"]))
    features: list[Feature] = []
    skipped: dict[str, list[int]] = {}
    for index, raw in enumerate(doc["features"]):
        feature = parse_feature(path, index, raw)
        if isinstance(feature, str):
            skipped.setdefault(feature, []).append(index)
        else:
            features.append(feature)
    report.num_skipped += sum(len(v) for v in skipped.values())
    if not features:
        raise InputError(
            path,
            f"no Polygon or MultiPolygon features among {report.num_features} "
            f"features ({_skip_summary(skipped)}); expected building footprints",
        )
    if skipped:
        logger.warning(
            "%s: skipped %d of %d features, not building footprints: %s",
            path,
            report.num_skipped,
            report.num_features,
            _skip_summary(skipped),
        )
    features, crs = to_projected(
        path, crs, features, options.crs, options.allow_degree_range
    )
    return Footprints(path, crs, features, report, t_start)


def _within_area(fp: Footprints, area) -> list[Feature]:
    """The features whose bounding box meets ``area`` (absolute bounds)."""
    bounds = shapely.bounds([f.geometry for f in fp.features])  # (N, 4)
    xmin, ymin, xmax, ymax = area
    keep = (
        (bounds[:, 2] >= xmin)
        & (bounds[:, 0] <= xmax)
        & (bounds[:, 3] >= ymin)
        & (bounds[:, 1] <= ymax)
    )
    if not keep.any():
        raise InputError(
            fp.path,
            f"none of its {len(fp.features)} footprints lies within the block's "
            f"area ({xmin:.0f}, {ymin:.0f}) - ({xmax:.0f}, {ymax:.0f}) "
            f"{fp.crs or ''} (is the map in another CRS than the priors?)",
        )
    if not keep.all():
        logger.info(
            "%s: %d of %d footprints within the block's area",
            fp.path.name, int(keep.sum()), len(keep),
        )  # fmt: skip
    return [f for f, k in zip(fp.features, keep, strict=True) if k]


def build_cadastre(
    fp: Footprints,
    options: CadastreOptions,
    origin: Sequence[float] | np.ndarray | None = None,
) -> Cadastre:
    """Steps 2-5 of :func:`load_cadastre` on parsed footprints."""
    path, crs, report = fp.path, fp.crs, fp.report
    features = fp.features
    if options.area is not None:
        features = _within_area(fp, options.area)
    bounds = check_metric(path, crs, features, options)

    # 2. Local frame.
    origin3 = choose_origin(bounds, origin, options)
    shift = (-float(origin3[0]), -float(origin3[1]))

    # 3. + 4. Validate / repair, dissolve, orient and clean, in the local frame.
    polygons: list[Polygon] = []
    owners: list[Feature] = []
    for feature in features:
        geometry = shapely.transform(feature.geometry, lambda c: c + shift)
        parts = valid_parts(path, feature, geometry, options, report)
        cleaned = [
            p
            for part in parts
            if (p := clean_polygon(part, options, report)) is not None
        ]
        if not cleaned:
            logger.warning(
                "%s: %s has no polygon of at least %g m^2 after cleaning; dropped",
                path,
                feature.label(),
                options.min_area_m2,
            )
            report.num_skipped += 1
            continue
        polygons.extend(cleaned)
        owners.extend([feature] * len(cleaned))
    if not polygons:
        raise InputError(
            path,
            "no building footprint is left after cleaning "
            f"(all smaller than {options.min_area_m2} m^2 or empty)",
        )

    # 5. Corners, edges, party walls, spatial index.
    cadastre = assemble(crs, origin3, polygons, owners, options)
    report.seconds = time.perf_counter() - fp.t_start
    cadastre.report = report
    logger.info(
        "cadastre %s: %d features -> %d buildings, %d corners (%d reflex), "
        "%d edges (%d party walls), %d repaired, %d skipped, %.2f s",
        path.name,
        report.num_features,
        cadastre.num_buildings,
        cadastre.num_corners,
        int(np.sum(cadastre.corner_angle_deg > 180.0)),
        cadastre.num_edges,
        int(np.sum(cadastre.edge_shared_fraction >= SHARED_WALL_FRACTION)),
        report.num_repaired,
        report.num_skipped,
        report.seconds,
    )
    return cadastre


def _skip_summary(skipped: dict[str, list[int]]) -> str:
    """'985 with geometry type 'LineString' (features 0, 1, 2, ...)'-like
    phrase, one part per reason."""
    parts = []
    for reason, indices in skipped.items():
        shown = ", ".join(str(i) for i in indices[:3])
        more = ", ..." if len(indices) > 3 else ""
        parts.append(f"{len(indices)} with {reason} (features {shown}{more})")
    return "; ".join(parts)
