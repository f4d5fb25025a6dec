"""Map discrepancies: footprints the images contradict.

Evidence per footprint: its corners' vertical edges, re-detected at the
final poses. In every registered image, the line segments that point at the
image's vertical vanishing point are drawn into an edge map; each corner the
image should see (inside the image, one of its walls facing the camera) is
sampled along its vertical (``num_samples`` heights between 1 m above the
ground and 0.5 m below the top: the eave, or for a building without one a
third of the height at which the views agree on its roof,
:func:`eaveless_tops`) and a sample is supported when a vertical edge passes
within ``support_px``. The same is done with the whole footprint shifted by
each offset of a grid (+-``max_shift_m``), so that ``support[b, s]`` is the
share of supported samples of building b under shift s. A footprint without
an eave too small for the height sweep (a shed) is not judged.

* A building not called shifted whose best support is below
  ``sweep_ratio`` times the block's median best support, and whose views
  agree best at the ground of its footprint (:mod:`.roof`, a height sweep
  of its interior; :func:`.roof.empty_site`): absent from the scene
  (demolished but mapped). The corners alone do not tell a demolished
  building from a present one whose corners the images do not show (e.g.
  where a building the map lacks adjoins it: the facade runs on past the
  mapped corner, and the unmapped building hides its other corners), nor
  from one the sweep cannot read (too few views): a standing building's
  views agree at its roof, an empty site's at the ground. Stray support of
  a demolished building's corners (neighbours' edges met under some shift)
  and an "eave" on its walls (in dense blocks, the edges of the buildings
  behind) do not count against the ground.
* A building whose best support comes with a shift longer than
  ``min_shift_m`` (fitted from the grid's best to its corners' vertical
  segments below a pixel, :func:`fitted_shifts`),
  beats the unshifted support by ``min_gain`` of itself, whose support is
  below ``shifted_ratio`` times the median unshifted and above it shifted,
  and that chance does not explain (:func:`chance_peaks`: the corner views
  seen at the shifted place against the building's own rate over all
  shifts, < 1 such peak expected): shifted (a consistent offset of all its
  corners). "Unshifted" and the gain are read in the views in which the
  shift moves the corners across their verticals (:class:`AcrossEvidence`):
  along a view a shift only slides the vertical along its own image.

Corners on another footprint's outline (party walls) are left out: the
neighbour's edge supports them whatever this footprint does.

Occlusion by other buildings is not modelled: it lowers a building's
support under every shift alike, so the tests are relative.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import shapely
from scipy.stats import binom

from obliq_colmap.colmap_io import read_model
from obliq_colmap.errors import InputError
from obliq_colmap.images import read_image
from obliq_colmap.parallel import WorkerPool, available_cores
from obliq_colmap.products.discrepancy_options import DiscrepancyOptions
from obliq_colmap.products.roof import (
    RoofView,
    blurred,
    empty_site,
    footprint_samples,
    height_profile,
    roof_heights,
    views_seeing,
)
from obliq_colmap.products.support import edge_offsets, edge_support

__all__ = ["DiscrepancyOptions", "classify", "find_discrepancies", "shift_grid"]

logger = logging.getLogger(__name__)


def shift_grid(options: DiscrepancyOptions) -> np.ndarray:
    """(S, 2) shifts (m); row 0 is (0, 0)."""
    k = np.arange(
        -options.max_shift_m, options.max_shift_m + 1e-9, options.shift_step_m
    )
    S = np.stack(np.meshgrid(k, k), -1).reshape(-1, 2)
    S = S[np.argsort(np.hypot(S[:, 0], S[:, 1]), kind="stable")]
    return S


@dataclass
class AcrossEvidence:
    """Per building and shift, over the corner views in which the shift moves
    the corner's vertical across its image (:func:`.support.across_shift`):
    how many (views), their supported samples under the shift (support) and
    without it (support0), and how many of them are seen (half the samples)
    under the shift (seen) and without it (seen0). All (B, S)."""

    views: np.ndarray
    support: np.ndarray
    support0: np.ndarray
    seen: np.ndarray
    seen0: np.ndarray

    @classmethod
    def zeros(cls, B: int, S: int) -> AcrossEvidence:
        return cls(*(np.zeros((B, S)) for _ in range(5)))

    def add(
        self, b: np.ndarray, sup: np.ndarray, seen: np.ndarray, across: np.ndarray
    ) -> None:
        """Add one image's corner views: b (K,) building of each, sup (K, S)
        supported samples, seen (K, S) bool, across (K, S) bool."""
        np.add.at(self.views, b, across)
        np.add.at(self.support, b, np.where(across, sup, 0))
        np.add.at(self.support0, b, np.where(across, sup[:, :1], 0))
        np.add.at(self.seen, b, across & seen)
        np.add.at(self.seen0, b, across & seen[:, :1])


def support_share(
    support: np.ndarray, views: np.ndarray, options: DiscrepancyOptions
) -> tuple[np.ndarray, np.ndarray]:
    """((B, S) share of each building's sampled corner views supported under
    each shift, (B,) its best shift's index)."""
    frac = support / np.maximum(views * options.num_samples, 1)[:, None]
    return frac, frac.argmax(axis=1)


def refined_shift(
    frac: np.ndarray, shifts: np.ndarray, best_i: np.ndarray, step: float
) -> np.ndarray:
    """(B, 2) the best shift refined below the grid's step: the mean of the
    shifts within one step of it (3 x 3), weighted by their support above
    the least of them. The 0.5 m test then meets the map's vertex noise
    (0.1-0.35 m) less often at the grid's smallest step past it (0.56 m).

    frac : (B, S) support; shifts : (S, 2); best_i : (B,) the best shift.
    """
    near = (
        np.abs(shifts[None, :, :] - shifts[best_i][:, None, :]).max(axis=2)
        <= step + 1e-9
    )  # (B, S)
    w = np.where(near, frac, np.inf)
    w = np.where(near, frac - w.min(axis=1, keepdims=True), 0.0)
    tot = w.sum(axis=1, keepdims=True)
    return np.where(tot > 0, (w @ shifts) / np.maximum(tot, 1e-12), shifts[best_i])


def fitted_shifts(
    building: np.ndarray,
    offset: np.ndarray,
    jac: np.ndarray,
    start: np.ndarray,
    options: DiscrepancyOptions,
    iterations: int = 5,
) -> tuple[np.ndarray, np.ndarray]:
    """(B, 2) shifts fitted to the corner views' edges, and (B,) how many
    corner views found an edge.

    Each corner view's edge lies ``offset`` (V,) px across the corner's
    image line at the shift ``start`` (B, 2) of its ``building`` (V,), and
    the line moves ``jac`` (V, 2) px across per metre of shift
    (:func:`.support.edge_offsets`; NaN offset: no edge). Per building the
    correction that moves the lines onto the edges, robustly (Huber at
    ``fit_huber_px``), held towards zero by a prior of one grid step: where
    the views move the corners across in one direction only, the other
    component stays the grid's.
    """
    B = len(start)
    ok = np.isfinite(offset)
    b, o, J = building[ok], offset[ok], jac[ok]
    ridge = (options.fit_huber_px / options.shift_step_m) ** 2 * np.eye(2)
    delta = np.zeros((B, 2))
    JJ = J[:, :, None] * J[:, None, :]  # (V, 2, 2)
    for _ in range(iterations):
        r = o - np.einsum("vj,vj->v", J, delta[b])
        w = np.minimum(1.0, options.fit_huber_px / np.maximum(np.abs(r), 1e-9))
        N = np.zeros((B, 2, 2))
        g = np.zeros((B, 2))
        np.add.at(N, b, w[:, None, None] * JJ)
        np.add.at(g, b, (w * o)[:, None] * J)
        delta = np.linalg.solve(N + ridge, g[..., None])[..., 0]
    return start + delta, np.bincount(b, minlength=B)


def chance_peaks(
    seen: np.ndarray, views: np.ndarray, best_i: np.ndarray, options: DiscrepancyOptions
) -> np.ndarray:
    """(B,) how many shifts as well seen as the best one chance would give.

    ``seen`` (B, S): corner views seen (half the samples on an edge) under
    each shift. A building's background rate is its mean over all shifts
    (clutter differs: trees, textured facades, neighbours' edges); the best
    shift's count is a binomial tail against it, times the number of
    distinct shift hypotheses, (2 max_shift / min_shift)^2: shifts closer
    than the smallest one we call are one hypothesis.
    """
    n = np.maximum(views, 1).astype(int)
    rate = np.clip(seen.mean(axis=1) / n, 1e-3, 1.0)
    k = seen[np.arange(len(seen)), best_i].astype(int)
    hypotheses = (2 * options.max_shift_m / options.min_shift_m) ** 2
    return binom.sf(k - 1, n, rate) * hypotheses


def classify(
    support: np.ndarray,
    views: np.ndarray,
    shifts: np.ndarray,
    has_eave: np.ndarray,
    options: DiscrepancyOptions,
    seen: np.ndarray | None = None,
    across: AcrossEvidence | None = None,
    fitted: np.ndarray | None = None,
) -> dict[str, np.ndarray]:
    """Per building: best shift, supports, score and verdict.

    Parameters
    ----------
    support : (B, S) supported samples; views : (B,) sampled corner views.
    has_eave : (B,) bool, the facade tracks found an eave on its walls (a
        demolished building has none: no absent verdict then).
    seen : (B, S) corner views seen under each shift (:func:`chance_peaks`);
        None: that test is left out.
    across : the support over the views in which each shift moves the
        corners across their verticals (:class:`AcrossEvidence`): "not seen
        in place" is judged there. None: over all views.
    fitted : (B, 2) the best shift fitted to the edges below the grid's
        step (:func:`fitted_shifts`; NaN where none); None or NaN: the
        grid's best refined by its neighbours (:func:`refined_shift`).

    Returns
    -------
    dict of (B,) arrays: judged, s0, best, shift (B, 2), gain, kind
    ("", "absent", "shifted"), score in [0, 1].
    """
    judged = views >= options.min_views
    frac, best_i = support_share(support, views, options)
    best = frac[np.arange(len(frac)), best_i]
    s0 = frac[:, 0]
    ref = float(np.median(best[judged])) if judged.any() else 0.0
    absent = judged & (best < options.absent_ratio * ref) & ~has_eave
    shift = refined_shift(frac, shifts, best_i, options.shift_step_m)
    if fitted is not None:
        shift = np.where(np.isfinite(fitted), fitted, shift)
    gain = (best - s0) / np.maximum(best, 1e-9)
    # "not seen in place" and the gain judged in the views in which the best
    # shift moves the corners across their verticals: in the others the
    # map's corner and the shifted one lie on the same image line, both are
    # seen, and the gain over all views is diluted (urban-101 DENW0000134:
    # 0.37 over all views, 0.77 over the 8 across). The gain there only
    # where those views alone are enough to judge a building (min_views).
    s0_unseen = s0
    if across is not None:
        r = np.arange(len(frac))
        n_across = across.views[r, best_i]
        den = np.maximum(n_across * options.num_samples, 1)
        fa0 = across.support0[r, best_i] / den
        fa = across.support[r, best_i] / den
        s0_unseen = np.where(n_across > 0, fa0, np.inf)
        gain_across = (fa - fa0) / np.maximum(fa, 1e-9)
        gain = np.where(
            n_across >= options.min_views, np.maximum(gain, gain_across), gain
        )
    shifted = (
        judged
        & ~absent
        & (np.hypot(shift[:, 0], shift[:, 1]) > options.min_shift_m)
        & (gain >= options.min_gain)
        & (s0_unseen < options.shifted_ratio * ref)
        & (best >= options.shifted_ratio * ref)
    )
    if seen is not None:
        shifted &= chance_peaks(seen, views, best_i, options) < 1.0
    kind = np.where(absent, "absent", np.where(shifted, "shifted", ""))
    score = np.where(
        judged, np.maximum(1.0 - best / max(ref, 1e-9), 0.0) * (best < ref), 0.0
    )
    score = np.where(shifted, np.maximum(score, gain), score)
    return {
        "judged": judged,
        "s0": s0,
        "best": best,
        "shift": shift,
        "gain": gain,
        "kind": kind,
        "score": np.clip(score, 0.0, 1.0),
    }


def shared_corners(cadastre, tol_m: float = 0.3) -> np.ndarray:
    """(C,) bool: corners within ``tol_m`` of another footprint's outline."""
    rings = [shapely.boundary(p) for p in cadastre.polygons]
    tree = shapely.STRtree(rings)
    pt, b = tree.query(
        shapely.points(cadastre.corner_xy), predicate="dwithin", distance=tol_m
    )
    other = b != cadastre.corner_building[pt]
    out = np.zeros(len(cadastre.corner_xy), bool)
    out[pt[other]] = True
    return out


def empty_sites(
    polygons: list,
    ground_z: np.ndarray,
    views: list[RoofView],
    options: DiscrepancyOptions,
) -> np.ndarray:
    """(B,) bool: the height sweep of each footprint's interior agrees best
    at the ground (:func:`.roof.empty_site`)."""
    up = np.arange(
        options.sweep_min_m, options.sweep_max_m + 1e-9, options.sweep_step_m
    )
    out = np.zeros(len(polygons), bool)
    cen = np.array([p.centroid.coords[0] for p in polygons]).reshape(-1, 2)
    sees = views_seeing(views, np.column_stack([cen, np.nan_to_num(ground_z)]))
    for b, poly in enumerate(polygons):
        xy = footprint_samples(
            poly, options.sweep_grid_m, options.sweep_inset_m, options.sweep_max_points
        )
        if len(xy) < options.sweep_min_points or not np.isfinite(ground_z[b]):
            continue
        # only the views that see the footprint's centre (the cost)
        vb = [views[i] for i in np.flatnonzero(sees[:, b])]
        ncc, n = height_profile(vb, xy, ground_z[b] + up)
        out[b] = empty_site(ncc, n, up, options.stand_height_m, options.empty_views)
    return out


def sweepable(polygons: list, options: DiscrepancyOptions) -> np.ndarray:
    """(B,) bool: the footprint holds about ``sweep_min_points`` interior
    points of the sweep's grid (its inset area over the grid cell)."""
    inner = shapely.buffer(np.asarray(polygons, dtype=object), -options.sweep_inset_m)
    return shapely.area(inner) >= options.sweep_min_points * options.sweep_grid_m**2


def eaveless_tops(
    polygons: list,
    ground_z: np.ndarray,
    eave_z: np.ndarray,
    views: list[RoofView],
    options: DiscrepancyOptions,
) -> np.ndarray:
    """(B,) the top of the sampled corner verticals (model z).

    The eave where the facade tracks found one; else ``eaveless_top_fraction``
    of the height at which the views agree on the roof (:func:`.roof.
    roof_height`, a sweep of ``top_sweep_points`` interior points), clipped
    to [``stand_height_m`` + 0.5, ``default_height_m``] above the ground;
    ``default_height_m`` where the sweep sees nothing standing or cannot
    run (fewer than ``stand_views`` views of the footprint's centre, no
    interior point).
    """
    top = np.where(np.isfinite(eave_z), eave_z, ground_z + options.default_height_m)
    up = np.arange(
        options.sweep_min_m, options.sweep_max_m + 1e-9, options.sweep_step_m
    )
    # a roof seen higher than this gives the default top anyway
    up = up[up <= options.default_height_m / options.eaveless_top_fraction]
    h = roof_heights(
        polygons,
        ground_z,
        ~np.isfinite(eave_z),
        views,
        up,
        options,
    )
    lo = options.stand_height_m + 0.5
    f = np.clip(options.eaveless_top_fraction * h, lo, options.default_height_m)
    return np.where(np.isfinite(h), ground_z + f, top)


def roof_views(block, image_path: Path, options: DiscrepancyOptions) -> list[RoofView]:
    views = []
    for im in block.images.values():
        gray, _ = read_image(image_path / im.name)
        if gray is not None:
            # blurred, kept as uint8: 36 images of 2.7 Mpx in ~100 MB
            g = blurred(gray, options.sweep_blur_px)
            views.append(
                RoofView(
                    np.clip(np.rint(g), 0, 255).astype(np.uint8),
                    block.cameras[im.camera_id],
                    im.cam_from_world,
                    image_path / im.name,
                )
            )
    return views


def _fit_to_edges(
    results: list,
    tasks: list[dict],
    cad,
    common: dict,
    support: np.ndarray,
    views: np.ndarray,
    options: DiscrepancyOptions,
) -> np.ndarray:
    """(B, 2) :func:`fitted_shifts` of the judged buildings from their
    grid's best shift, over every image's corner views (``results`` of
    :func:`.support.edge_support`, one per task); NaN where no corner view
    found an edge."""
    start = common["shifts"][support_share(support, views, options)[1]]
    judged = views >= options.min_views
    z0, z1 = common["corner_z0"], common["corner_z1"]
    parts = []
    for (k, _, _, segments), task in zip(results, tasks, strict=True):
        b = cad.corner_building[k]
        use = judged[b] & np.isfinite(z0[k]) & np.isfinite(z1[k])
        if not use.any() or len(segments) == 0:
            continue
        k, b = k[use], b[use]
        xy = cad.corner_xy[k] + start[b]
        off, jac = edge_offsets(
            task["camera"],
            task["pose"],
            segments,
            np.column_stack([xy, z0[k]]),
            np.column_stack([xy, z1[k]]),
            options.fit_window_px,
        )
        parts.append((b, off, jac))
    out = np.full(start.shape, np.nan)
    if not parts:
        return out
    b, off, jac = (np.concatenate(x) for x in zip(*parts, strict=True))
    fit, n = fitted_shifts(b, off, jac, start, options)
    return np.where((n > 0)[:, None], fit, out)


def find_discrepancies(
    input_path,
    image_path,
    c,
    heights,
    options: DiscrepancyOptions,
    num_workers: int = 0,
    block=None,
    views: list[RoofView] | None = None,
) -> dict:
    """The discrepancy layer (GeoJSON dict, absolute coordinates) of one
    registration: one feature per judged footprint with its score.
    ``block`` (:func:`~obliq_colmap.colmap_io.read_model` of ``input_path``)
    and ``views`` (its blurred images, :func:`roof_views`), if already read."""
    block = block if block is not None else read_model(input_path)
    cad = c.cadastre
    image_path = Path(image_path)
    zg = heights.ground_z[cad.corner_building]
    rv = views if views is not None else roof_views(block, image_path, options)
    top = eaveless_tops(cad.polygons, heights.ground_z, heights.eave_z, rv, options)
    top = top[cad.corner_building]
    common = {
        "options": options,
        "corner_xy": cad.corner_xy,
        "corner_wall_normals": cad.edge_normal[cad.corner_edges],
        "corner_z0": zg + 1.0,
        "corner_z1": np.maximum(top - 0.5, zg + 1.5),
        "shifts": shift_grid(options),
    }
    # A corner on another footprint's outline (a terrace's party wall) is
    # supported by that neighbour's edge whatever this footprint does.
    common["corner_z0"] = np.where(shared_corners(cad), np.nan, common["corner_z0"])
    tasks = []
    for im in block.images.values():
        p = image_path / im.name
        if not p.is_file():
            raise InputError(p, "image of the model not found under --image_path")
        tasks.append(
            dict(
                common,
                path=p,
                camera=block.cameras[im.camera_id],
                pose=im.cam_from_world,
            )
        )
    workers = num_workers or available_cores()
    with WorkerPool(min(workers, len(tasks))) as pool:
        results = pool.map(edge_support, tasks, "vertical edges")
    B, S = len(cad.polygons), len(common["shifts"])
    support, views = np.zeros((B, S)), np.zeros(B)
    views_seen = np.zeros((B, S))
    ac = AcrossEvidence.zeros(B, S)
    for k, sup, across, _ in results:
        b = cad.corner_building[k]
        np.add.at(support, b, sup)
        np.add.at(views, b, 1.0)
        # a corner view is seen under a shift when half its vertical is
        seen = 2 * sup >= options.num_samples
        np.add.at(views_seen, b, seen)
        ac.add(b, sup, seen, across)
    # a shed without an eave: neither its height nor its roof can be read
    views = np.where(
        np.isfinite(heights.eave_z) | sweepable(cad.polygons, options), views, 0.0
    )
    fitted = None
    if options.fit_shift:
        fitted = _fit_to_edges(results, tasks, cad, common, support, views, options)
    v = classify(
        support,
        views,
        common["shifts"],
        np.isfinite(heights.eave_z),
        options,
        views_seen,
        ac if options.judge_across else None,
        fitted,
    )
    # absent: corners seen clearly nowhere, and the views agree on the ground
    judged = v["judged"]
    ref = float(np.median(v["best"][judged])) if judged.any() else 0.0
    cand = np.flatnonzero(
        judged & (v["kind"] != "shifted") & (v["best"] < options.sweep_ratio * ref)
    )
    if len(cand):
        empty = empty_sites(
            [cad.polygons[b] for b in cand], heights.ground_z[cand], rv, options
        )
        was = v["kind"][cand] == "absent"
        logger.info(
            "discrepancies: %d of %d weakly supported footprints seen empty "
            "(%d of the %d the corners alone called absent)",
            empty.sum(),
            len(cand),
            (empty & was).sum(),
            was.sum(),
        )
        v["kind"][cand] = np.where(empty, "absent", "")
        # a site the sweep sees standing or cannot read keeps its low-support
        # score unless the corners alone had called it absent
        sc = v["score"][cand]
        v["score"][cand] = np.where(empty, np.maximum(sc, 0.5), np.where(was, 0.0, sc))
    o = c.georef.origin
    feats = []
    for b in np.flatnonzero(v["judged"]):
        geom = shapely.affinity.translate(cad.polygons[b], o[0], o[1])
        props = {
            "id": str(cad.building_ids[b]),
            "score": round(float(v["score"][b]), 3),
            "flagged": bool(v["kind"][b] != ""),
            "kind": str(v["kind"][b]) or None,
            "support": round(float(v["s0"][b]), 3),
            "best_support": round(float(v["best"][b]), 3),
            "best_shift_m": [round(float(x), 2) for x in v["shift"][b]],
            "corner_views": int(views[b]),
        }
        feats.append(
            {
                "type": "Feature",
                "properties": props,
                "geometry": shapely.geometry.mapping(geom),
            }
        )
    logger.info(
        "discrepancies: %d of %d judged footprints flagged",
        sum(f["properties"]["flagged"] for f in feats),
        len(feats),
    )
    doc = {"type": "FeatureCollection"}
    if cad.crs:
        doc["crs"] = {"type": "name", "properties": {"name": cad.crs}}
    doc["features"] = feats
    return doc
