"""Benchmark of ``obliq-colmap export_products`` against ground truth (issue 28).

    PYTHONPATH=. .venv/bin/python scripts/bench/products.py \\
        --input_path OUT_MODEL --scene SCENE [--products_path DIR] \\
        [--output_path R.json]

OUT_MODEL is ``register``'s result on SCENE: a synthetic scene
(``obliq-colmap synth``; truth: the city rebuilt from its seed) or an
external one (``../shared/data/external_oblique/*``: ``gt_terrain.npz``,
``gt_buildings.json``). Without ``--products_path`` the products are made
(with the images) into a temporary folder. Measured, from the written files:

* terrain: RMSE of ``terrain.asc`` against the true terrain at the cell
  centres after removing ONE vertical offset (the median difference: the
  priors' datum is arbitrary), over (a) the cells with a recovered ground
  corner (a map corner in points3D) within 20 m, the issue's measure, where
  the grid has a value, and (b) every cell the grid gives; coverage of (a);
* eave height above ground (``buildings.geojson``) against the truth, over
  the mapped buildings present in the scene with facade tracks: median and
  p90 of the absolute error, and how many got a height (all, and by the
  rule that gave it, ``eave_support``); and the coverage:
  of the mapped buildings present that the block sees (the footprint's
  centre at its true eave in >= 3 true images), the share with a height;
* discrepancies (``discrepancies.geojson``): positives = mapped buildings
  absent from the scene or shifted by > 0.5 m; precision and recall over the
  judged footprints, and recall over all positives with constrained points;
* buildings missing from the map (``missing.geojson``): precision = the
  reported features that overlap a true missing building's footprint (the
  others are labelled by what they overlap: a tree crown, a mapped
  building, nothing); recall = the missing buildings the block sees (the
  footprint's centre at its eave in >= 3 true images) that a reported
  feature overlaps; the same for the reported features whose walls are
  confirmed too (``walls_confirmed``).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import shapely
import shapely.affinity
import shapely.geometry
from scipy.spatial import cKDTree

from obliq_colmap.products.constraints import load_constraints
from obliq_colmap.products.run import make_products
from obliq_colmap.synthetic.city import Terrain


def read_asc(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ny, nx) X, Y of the cell centres and Z (NaN for NODATA)."""
    lines = path.read_text().splitlines()
    head = {k.lower(): float(v) for k, v in (ln.split() for ln in lines[:6])}
    Z = np.loadtxt(lines[6:], ndmin=2)
    Z[np.isclose(Z, head["nodata_value"])] = np.nan
    ny, nx = Z.shape
    c = head["cellsize"]
    xs = head["xllcorner"] + (np.arange(nx) + 0.5) * c
    ys = head["yllcorner"] + (ny - np.arange(ny) - 0.5) * c
    X, Y = np.meshgrid(xs, ys)
    return X, Y, Z


def truth(scene: Path):
    """(terrain (M,2)->(M,) absolute, {map id: (present, shift_m, eave_height)})."""
    if (scene / "gt_terrain.npz").is_file():  # external
        t = np.load(scene / "gt_terrain.npz")
        T = Terrain(float(t["x0"]), float(t["y0"]), float(t["cell"]), t["Z"])
        gb = json.loads((scene / "gt_buildings.json").read_text())
        b = {}
        for x in gb["buildings"]:
            if x["state"] == "mapped":
                base = min(min(r) for r in x["base_z"])
                b[x["map_id"]] = (
                    True,
                    float(np.hypot(*x["map_shift"])),
                    x["eave_z"] - base,
                )
        for x in gb["map_only"]:
            b[x["map_id"]] = (False, 0.0, np.nan)
        return (lambda q: T.height(q[:, 0], q[:, 1])), b
    from obliq_colmap.synthetic.scene_io import load_scene

    sc = load_scene(scene)
    o = sc.origin

    def terrain(q):
        return sc.city.terrain.height(q[:, 0] - o[0], q[:, 1] - o[1]) + o[2]

    b = {
        str(x["id"]): (x["in_scene"], float(np.hypot(*x["shift_m"])), x["height_m"])
        for x in sc.buildings["buildings"]
        if x["in_map"]
    }
    return terrain, b


def split_truth(scene: Path) -> dict:
    """{map id: [(footprint, present, shift_m, eave height above its ground),
    ...]} for the map ids the external scenes give to more than one
    footprint (a house and its garage mapped as one multipolygon, or a
    standing building and a demolished one, split into parts by the
    cadastre's reader; shift and eave are 0 and NaN for a demolished one):
    each part is scored against the footprint it covers
    (:func:`part_truth`), not against whichever of them :func:`truth` kept
    for the id."""
    import shapely

    if not (scene / "gt_terrain.npz").is_file():  # ours: one footprint per id
        return {}
    gb = json.loads((scene / "gt_buildings.json").read_text())
    out: dict = {}
    for x in gb["buildings"]:
        if x["state"] == "mapped":
            base = min(min(r) for r in x["base_z"])
            poly = shapely.Polygon(x["footprint"][0], x["footprint"][1:])
            shift = float(np.hypot(*x["map_shift"]))
            out.setdefault(x["map_id"], []).append(
                (poly, True, shift, x["eave_z"] - base)
            )
    for x in gb["map_only"]:
        poly = shapely.Polygon(x["footprint"][0], x["footprint"][1:])
        out.setdefault(x["map_id"], []).append((poly, False, 0.0, np.nan))
    return {k: v for k, v in out.items() if len(v) > 1}


def part_truth(gt: dict, split: dict, map_id: str, polygon) -> tuple | None:
    """(present, shift_m, eave height) of the map part ``polygon``
    (absolute) of ``map_id``: those of the footprint of the id it overlaps
    most (:func:`split_truth`), or the id's in ``gt`` (:func:`truth`) where
    it names one footprint; None for an id the truth does not know."""
    if map_id not in split:
        return gt.get(map_id)
    areas = [polygon.intersection(p).area for p, *_ in split[map_id]]
    return split[map_id][int(np.argmax(areas))][1:]


def positive(present: bool, shift_m: float, *_) -> bool:
    """A discrepancy to find: demolished, or shifted by more than 0.5 m."""
    return not present or shift_m > 0.5


def missing_truth(scene: Path):
    """(missing footprints, their eave z, tree crowns, other buildings), all
    absolute; shapely geometries."""
    import shapely

    if (scene / "gt_buildings.json").is_file() and (scene / "gt_terrain.npz").is_file():
        gb = json.loads((scene / "gt_buildings.json").read_text())

        def poly(b):
            return shapely.Polygon(b["footprint"][0], b["footprint"][1:])

        miss = [b for b in gb["buildings"] if b["state"] == "missing"]
        other = [poly(b) for b in gb["buildings"] if b["state"] != "missing"]
        trees = [shapely.Point(t[:2]).buffer(t[3]) for t in gb["trees"]]
        return [poly(b) for b in miss], [b["eave_z"] for b in miss], trees, other
    from obliq_colmap.synthetic.scene_io import load_scene

    sc = load_scene(scene)
    o = sc.origin
    miss, eave, other = [], [], []
    for b in sc.city.buildings:
        fp = shapely.affinity.translate(b.footprint, o[0], o[1])
        if b.in_scene and not b.in_map:
            miss.append(fp)
            eave.append(b.base_z + b.height_m + o[2])
        elif b.in_scene:
            other.append(fp)
    # the rebuilt city keeps no trees (only its mesh has them): a false
    # report on a synthetic scene is labelled "nothing" then.
    return miss, eave, [], other


def seen_by(scene: Path, xyz: np.ndarray, min_images: int = 3) -> np.ndarray:
    """(N,) bool: at least ``min_images`` true cameras (``scene/gt``) have
    the absolute point in front and inside the image."""
    import pycolmap

    rec = pycolmap.Reconstruction(str(scene / "gt"))
    n = np.zeros(len(xyz), int)
    for im in rec.images.values():
        cam = rec.cameras[im.camera_id]
        T = im.cam_from_world()
        Xc = xyz @ T.rotation.matrix().T + T.translation
        front = Xc[:, 2] > 0
        uv = np.full((len(xyz), 2), -1.0)
        if front.any():
            uv[front] = cam.img_from_cam(Xc[front])
        n += (
            front
            & (uv[:, 0] >= 0)
            & (uv[:, 0] < cam.width)
            & (uv[:, 1] >= 0)
            & (uv[:, 1] < cam.height)
        )
    return n >= min_images


def score_missing(scene: Path, prod: Path) -> dict:
    import shapely

    doc = json.loads((prod / "missing.geojson").read_text())
    miss, eave, trees, other = missing_truth(scene)
    cen = np.array(
        [[*p.centroid.coords[0], z] for p, z in zip(miss, eave, strict=True)]
    )
    seen = seen_by(scene, cen.reshape(-1, 3)) if len(miss) else np.zeros(0, bool)
    res = {"missing_in_scene": len(miss), "missing_seen": int(seen.sum())}
    for name, sel in (
        ("reported", lambda p: p["reported"]),
        ("walls_confirmed", lambda p: p["reported"] and p["walls_confirmed"]),
    ):
        feats = [f for f in doc["features"] if sel(f["properties"])]
        hit: set[int] = set()
        labels = {"missing": 0, "tree": 0, "mapped": 0, "nothing": 0}
        for f in feats:
            g = shapely.geometry.shape(f["geometry"])
            k = [i for i, m in enumerate(miss) if m.intersects(g)]
            hit |= set(k)
            if k:
                labels["missing"] += 1
            elif any(o.intersects(g) for o in other):
                labels["mapped"] += 1
            elif any(t.intersects(g) for t in trees):
                labels["tree"] += 1
            else:
                labels["nothing"] += 1
        found = sum(bool(seen[i]) for i in hit)
        res[name] = {
            "features": len(feats),
            "precision": round(labels["missing"] / max(len(feats), 1), 3),
            "labels": labels,
            "missing_found": len(hit),
            "recall_seen": round(found / max(int(seen.sum()), 1), 3),
        }
    return res


def error_figures(e: np.ndarray) -> dict:
    """Median and p90 of the absolute errors ``e`` (N,), None where N = 0."""
    return {
        "median_abs_error_m": round(float(np.median(e)), 3) if len(e) else None,
        "p90_abs_error_m": round(float(np.percentile(e, 90)), 3) if len(e) else None,
    }


def eave_coverage(
    c, gt: dict, split: dict, feats: list, terrain, scene: Path
) -> tuple[int, int]:
    """(the mapped buildings present that the block sees: the footprint's
    centre at its true eave in >= 3 true images, those of them with an eave
    height in ``buildings.geojson``)."""
    o = c.georef.origin
    ids = [str(i) for i in c.cadastre.building_ids]
    has = {
        f["properties"]["id"]
        for f in feats
        if f["properties"]["eave_height"] is not None
    }
    rows, parts, eave = [], [], []
    for b, i in enumerate(ids):
        part = shapely.affinity.translate(c.cadastre.polygons[b], *o[:2])
        g = part_truth(gt, split, i, part)
        if g is not None and g[0] and np.isfinite(g[2]):
            rows.append(b)
            parts.append(part)
            eave.append(g[2])
    if not rows:
        return 0, 0
    xy = np.array([p.centroid.coords[0] for p in parts])
    z = terrain(xy) + np.array(eave)
    seen = seen_by(scene, np.column_stack([xy, z]))
    got = [ids[b] in has for b in np.asarray(rows)[seen]]
    return int(seen.sum()), int(sum(got))


def score(model: Path, scene: Path, prod: Path) -> dict:
    terrain, gt = truth(scene)
    c = load_constraints(model, scene / "cadastre.geojson")
    o = c.georef.origin
    X, Y, Z = read_asc(prod / "terrain.asc")
    q = np.column_stack([X.ravel(), Y.ravel()])
    zt = terrain(q).reshape(X.shape)
    d, _ = cKDTree(c.ground_xyz[:, :2] + o[:2]).query(q)
    near = (d <= 20.0).reshape(X.shape)
    has = np.isfinite(Z)
    off = float(np.median((Z - zt)[near & has]))
    err = Z - zt - off
    res = {
        "terrain": {
            "vertical_offset_m": round(off, 3),
            "rmse_near_corners_m": round(
                float(np.sqrt(np.mean(err[near & has] ** 2))), 3
            ),
            "coverage_near_corners": round(float((near & has).sum() / near.sum()), 3),
            "cells_near_corners": int(near.sum()),
            "rmse_all_cells_m": round(float(np.sqrt(np.nanmean(err[has] ** 2))), 3),
            "cells": int(has.sum()),
        }
    }
    feats = json.loads((prod / "buildings.geojson").read_text())["features"]
    split = split_truth(scene)
    e, support, n_seen = [], [], 0
    for f in feats:
        p = f["properties"]
        g = part_truth(gt, split, p["id"], shapely.geometry.shape(f["geometry"]))
        if g is None or not g[0] or p["num_facade_tracks"] == 0:
            continue
        n_seen += 1
        if p["eave_height"] is not None:
            e.append(p["eave_height"] - g[2])
            support.append(p.get("eave_support"))
    e, support = np.abs(np.array(e)), np.array(support, dtype=object)
    n_block, n_block_height = eave_coverage(c, gt, split, feats, terrain, scene)
    res["eave_height"] = {
        "buildings_with_tracks": n_seen,
        "with_height": len(e),
        "seen_by_the_block": n_block,
        "coverage_of_seen": round(n_block_height / max(n_block, 1), 3),
        **error_figures(e),
        "by_support": {
            str(k): {
                "with_height": int((support == k).sum()),
                **error_figures(e[support == k]),
            }
            for k in dict.fromkeys(support.tolist())
        },
    }
    disc = prod / "discrepancies.geojson"
    if disc.is_file():
        fs = json.loads(disc.read_text())["features"]
        # per judged part: a positive when the footprint it covers is gone
        # or shifted by > 0.5 m (:func:`part_truth`)
        flags = np.array([f["properties"]["flagged"] for f in fs], bool)
        truths = [
            part_truth(
                gt, split, f["properties"]["id"], shapely.geometry.shape(f["geometry"])
            )
            for f in fs
        ]
        part_pos = np.array([t is not None and positive(*t) for t in truths], bool)
        # an id is a positive when any of its footprints is (the "seen"
        # recall counts ids; the external maps' split ids have one judged part)
        pos = {k for k, g in gt.items() if positive(*g)}
        pos |= {k for k, v in split.items() if any(positive(*t[1:]) for t in v)}
        seen_ids = {
            str(c.cadastre.building_ids[b])
            for b in c.cadastre.corner_building[c.corner_index]
        }
        seen_ids |= {str(c.cadastre.building_ids[b]) for b in c.facade_building[:, 1]}
        tp = int((flags & part_pos).sum())
        res["discrepancies"] = {
            "judged": len(fs),
            "flagged": int(flags.sum()),
            "positives_judged": int(part_pos.sum()),
            "positives_seen": len(pos & seen_ids),
            "true_positives": tp,
            "precision": round(tp / max(int(flags.sum()), 1), 3),
            "recall_judged": round(tp / max(int(part_pos.sum()), 1), 3),
            "recall_seen": round(tp / max(len(pos & seen_ids), 1), 3),
        }
    if (prod / "missing.geojson").is_file():
        res["missing_from_map"] = score_missing(scene, prod)
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--input_path", required=True, type=Path)
    ap.add_argument("--scene", required=True, type=Path)
    ap.add_argument("--products_path", type=Path)
    ap.add_argument("--output_path", type=Path)
    a = ap.parse_args()
    t0 = time.time()
    with tempfile.TemporaryDirectory() as tmp:
        prod = a.products_path
        if prod is None:
            prod = Path(tmp) / "products"
            make_products(
                a.input_path, a.scene / "cadastre.geojson", prod, a.scene / "images"
            )
        res = {"input_path": str(a.input_path), "scene": str(a.scene)}
        res.update(score(a.input_path, a.scene, prod))
    res["time_s"] = round(time.time() - t0, 1)
    text = json.dumps(res, indent=1)
    print(text)
    if a.output_path:
        a.output_path.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
