"""``obliq-colmap report``: :func:`build_report` reads a result model (its
report.json, georef.json and poses), the priors, the images and the map, and
writes the report folder atomically: ``index.html``, ``report.json`` and
``images/`` with the before / after overlays.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from tqdm import tqdm

from obliq_colmap.cadastre import load_cadastre
from obliq_colmap.colmap_io import Block, read_georef, read_model
from obliq_colmap.errors import InputError
from obliq_colmap.files import AtomicFolder
from obliq_colmap.images import read_image
from obliq_colmap.report.overlays import project_edges, write_overlay
from obliq_colmap.report.page import ImageRow, render_page
from obliq_colmap.report.svg import PlanLayer, histogram_svg, plan_svg

__all__ = ["PAGE_FILE", "ReportOptions", "build_report"]

logger = logging.getLogger(__name__)

PAGE_FILE = "index.html"
_RED, _GREEN = (40, 40, 230), (60, 200, 60)  # BGR


@dataclass
class ReportOptions:
    """Paths of ``obliq-colmap report`` (as its options).

    ``priors_path``: the priors model; default the ``priors_path`` recorded
    in the run's report.json (None: no "before" overlays).
    """

    input_path: Path
    image_path: Path
    cadastre_path: Path
    output_path: Path
    priors_path: Path | None = None


def _read_run(model_path: Path) -> dict[str, Any]:
    path = model_path / "report.json"
    if not path.is_file():
        raise InputError(
            path, "no report.json: --input_path must be a model written by register"
        )
    try:
        run = json.loads(path.read_text())
    except ValueError as exc:
        raise InputError(path, f"not valid JSON: {exc}") from None
    if not isinstance(run, dict) or not isinstance(run.get("images"), dict):
        raise InputError(path, "no 'images' section: not a register run report")
    return run


def _centres(block: Block | None, names: list[str]) -> np.ndarray:
    """(K, 2) horizontal centres of the named images; NaN where absent."""
    out = np.full((len(names), 2), np.nan)
    if block is None:
        return out
    by_name = {im.name: im for im in block.images.values()}
    for k, n in enumerate(names):
        if n in by_name:
            out[k] = by_name[n].cam_from_world.center[:2]
    return out


def _overlays(
    image: np.ndarray,
    edge_xy: np.ndarray,
    ground: float,
    name: str,
    blocks: dict[str, Block | None],
    folder: Path,
) -> dict[str, tuple[str, str] | None]:
    """Draw and write the before / after overlays of one image."""
    out: dict[str, tuple[str, str] | None] = {}
    for which, block in blocks.items():
        im = None
        if block is not None:
            im = next((r for r in block.images.values() if r.name == name), None)
        if im is None:
            out[which] = None
            continue
        cam = block.cameras[im.camera_id]
        px = project_edges(edge_xy, cam, im.cam_from_world, ground)
        color, label = (
            (_RED, "map with the priors' pose (before)")
            if which == "before"
            else (_GREEN, "map with the registered pose (after)")
        )
        full, thumb = write_overlay(
            image, px, color, label, folder / "images", f"{Path(name).stem}_{which}"
        )
        out[which] = (f"images/{full}", f"images/{thumb}")
    return out


def build_report(options: ReportOptions) -> Path:
    """Write the report folder; returns the path of its page.

    Raises
    ------
    InputError
        Missing or invalid model, report.json, map, image folder or priors;
        an existing non-empty output folder.
    """

    model_path = Path(options.input_path)
    run = _read_run(model_path)
    block = read_model(model_path)
    georef = read_georef(model_path)
    image_path = Path(options.image_path)
    if not image_path.is_dir():
        raise InputError(image_path, "image folder does not exist")
    # register records the priors it read (as "priors_path", or its own
    # option name "input_path"); an explicit --priors_path wins
    priors_path = options.priors_path or run.get("priors_path") or run.get("input_path")
    priors = None
    notes = []
    if priors_path is not None:
        priors = read_model(priors_path).shifted(georef.origin)
    else:
        notes.append(
            "No priors model given (--priors_path) nor recorded in report.json: "
            "no 'before' overlays and no priors' centres."
        )
        logger.warning("no priors model: the report has no 'before' overlays")
    cad = load_cadastre(options.cadastre_path, origin=georef.origin)
    names = list(run["images"])
    z0 = float(georef.origin[2])
    default_ground = float(
        np.nanmedian(
            [
                e["ground_height_m"]
                for e in run["images"].values()
                if e.get("ground_height_m") is not None
            ]
            or [z0]
        )
    )
    rows = []
    with AtomicFolder(options.output_path) as tmp:
        (tmp / "images").mkdir()
        for name in tqdm(names, desc="report overlays", unit="image"):
            entry = run["images"][name]
            image, _ = read_image(image_path / name, color=True)
            if image is None:
                logger.warning("%s: cannot read; no overlays", image_path / name)
                rows.append(ImageRow(name, entry, None, None))
                continue
            g = entry.get("ground_height_m")
            ground = (default_ground if g is None else float(g)) - z0
            files = _overlays(
                image,
                cad.edge_xy,
                ground,
                name,
                {"before": priors, "after": block},
                tmp,
            )
            rows.append(ImageRow(name, entry, files["before"], files["after"]))
        page = render_page(
            run, rows, _histograms(run), _plans(run, cad, priors, block, names), notes
        )
        (tmp / PAGE_FILE).write_text(page, encoding="utf-8")
        (tmp / "report.json").write_text(json.dumps(run, indent=2) + "\n")
    return Path(options.output_path) / PAGE_FILE


def _histograms(run: dict[str, Any]) -> list[str]:
    images = run["images"]
    facades = run.get("facades", {}).get("images", {})
    unc = run.get("uncertainty", {}).get("images", {})
    stage2 = [e.get("residual_rms_px") for e in images.values()]
    # the last bundle may have held images its verdicts then left out
    written = {n for n, e in images.items() if e.get("status") == "registered"}
    bundle = [
        f.get("bundle_rms_px") or [None, None]
        for n, f in facades.items()
        if n in written
    ]
    sd = [u.get("predicted_sd_px") for u in unc.values()]

    def arr(v: list) -> np.ndarray:
        return np.array([np.nan if x is None else x for x in v], float)

    return [
        histogram_svg(arr(stage2), "stage 2: map corners", "residual RMS px"),
        histogram_svg(arr([b[0] for b in bundle]), "bundle: vertical", "RMS px"),
        histogram_svg(arr([b[1] for b in bundle]), "bundle: horizontal", "RMS px"),
        histogram_svg(arr(sd), "bundle: predicted sd", "px"),
    ]


def _plans(
    run: dict[str, Any], cad, priors: Block | None, block: Block, names: list[str]
) -> list[str]:
    rings = [np.asarray(p.exterior.coords)[:, :2] for p in cad.polygons]
    unc = run.get("uncertainty", {}).get("images", {})
    ell = np.array(
        [
            [np.nan if v is None else v for v in unc[n]["horizontal_ellipse_m"]]
            if n in unc and unc[n].get("horizontal_ellipse_m")
            else [np.nan] * 3
            for n in names
        ],
        float,
    ).reshape(len(names), 3)
    before, after = _centres(priors, names), _centres(block, names)
    return [
        plan_svg(rings, PlanLayer(names, before, after), "Camera positions"),
        plan_svg(
            rings,
            PlanLayer(names, np.full_like(before, np.nan), after, ell),
            "Horizontal position uncertainty",
        ),
    ]
