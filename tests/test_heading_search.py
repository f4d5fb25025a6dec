"""Priors with positions only (geo.txt): the heading searched in stage 2 (issue 29)."""

from __future__ import annotations

from pathlib import Path

import pycolmap
import pytest

from obliq_colmap.cli import main
from obliq_colmap.evaluate import EvaluateOptions, evaluate_model

SAMPLE = Path(__file__).resolve().parents[1] / "data_samples" / "oblique_small"


def _geo_txt(path: Path, names: set[str] | None = None) -> Path:
    rec = pycolmap.Reconstruction(str(SAMPLE / "priors"))
    lines = ["EPSG:25832"]
    for i in sorted(rec.reg_image_ids()):
        im = rec.images[i]
        if names is None or im.name in names:
            c = im.projection_center()
            lines.append(f"{im.name} {c[0]:.3f} {c[1]:.3f} {c[2]:.3f}")
    path.write_text("\n".join(lines) + "\n")
    return path


@pytest.mark.slow
def test_position_only_priors_register_by_heading_search(tmp_path):
    """One image per head, the priors' positions (8 m off) and no rotation:
    each image registered within 2 px of the truth, as with full priors."""
    names = {"N_00.jpg", "E_01.jpg", "S_10.jpg", "W_11.jpg"}
    geo = _geo_txt(tmp_path / "geo.txt", names)
    out = tmp_path / "out"
    rc = main(
        ["register", "--image_path", str(SAMPLE / "images"), "--cadastre_path",
         str(SAMPLE / "cadastre.geojson"), "--input_path", str(geo),
         "--camera_path", str(SAMPLE / "priors"), "--output_path", str(out),
         "--stop_after", "initial", "--no_progress"]
    )  # fmt: skip
    assert rc == 0
    options = EvaluateOptions(vertical_offset="search", across_vertical=True)
    result = evaluate_model(out, SAMPLE, options)
    means = {im.name: im.mean_deviation_px for im in result.images if im.name in names}
    assert len(means) == 4 and max(means.values()) < 2.0, means


def test_position_only_priors_refused_when_the_search_is_off(tmp_path, capsys):
    geo = _geo_txt(tmp_path / "geo.txt")
    rc = main(
        ["register", "--image_path", str(SAMPLE / "images"), "--cadastre_path",
         str(SAMPLE / "cadastre.geojson"), "--input_path", str(geo),
         "--camera_path", str(SAMPLE / "priors"), "--output_path",
         str(tmp_path / "out"), "--heading_step", "0"]
    )  # fmt: skip
    assert rc == 2 and "positions only" in capsys.readouterr().err
