"""The stage's entry: :func:`load_cadastre`, GeoJSON file -> :class:`Cadastre`."""

from __future__ import annotations

import logging
import time
from collections.abc import Sequence
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
        projected metric CRS. Other geometry types and null geometries are
        skipped with a warning.
    options : CadastreOptions, optional
        Cleaning options; the defaults suit 1 cm to 10 cm cadastral maps.
    origin : (2,) or (3,) array-like, optional
        Absolute coordinates (m) of the local origin, e.g. to share a frame
        with a priors model. Default: the centre of the map's bounds rounded to
        ``options.origin_rounding_m``, with z = 0.

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
        be repaired (or ``repair_invalid`` is False), coordinates in degrees.
    """
    t_start = time.perf_counter()
    options = CadastreOptions() if options is None else options
    path = Path(path)
    doc = read_document(path)
    crs = parse_crs(path, doc.get("crs"))
    report = CadastreReport(num_features=len(doc["features"]))

    # 1. Parse the features (absolute coordinates).
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
    report.seconds = time.perf_counter() - t_start
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
