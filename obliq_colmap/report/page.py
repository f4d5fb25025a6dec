"""The report's HTML page: one self-contained file (inline CSS and SVG, the
overlays as relative links to JPEGs next to it, no script from the network).

:func:`render_page` takes the run report (as ``register`` wrote it), one
:class:`ImageRow` per image and the figures' SVG; a small inline script
counts the images that loaded and writes the count into ``#image-check``
(the browser test reads it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from html import escape
from typing import Any

from obliq_colmap.report.uncertainty import TRUST_NOTE

__all__ = ["ImageRow", "render_page"]

_CSS = """
body { font-family: sans-serif; margin: 20px; color: #222; }
table { border-collapse: collapse; margin: 10px 0 24px; font-size: 13px; }
th, td { border: 1px solid #ccc; padding: 3px 6px; text-align: right; }
th { background: #eee; } td.l { text-align: left; }
td img { display: block; width: 240px; }
tr.bad td { background: #fde8e8; } tr.warn td { background: #fff6d9; }
.note { max-width: 1100px; font-size: 14px; }
.figs { display: flex; flex-wrap: wrap; gap: 12px; }
"""

_CHECK = """
<p id="image-check">images: not checked (scripts off)</p>
<script>
window.addEventListener('load', function () {
  var imgs = document.images, ok = 0;
  for (var i = 0; i < imgs.length; i++) {
    if (imgs[i].complete && imgs[i].naturalWidth > 0) { ok++; }
  }
  var p = document.getElementById('image-check');
  p.textContent = 'images loaded: ' + ok + ' / ' + imgs.length;
  p.setAttribute('data-loaded', ok);
  p.setAttribute('data-total', imgs.length);
});
</script>
"""


@dataclass
class ImageRow:
    """One image of the table: its run-report entry and its overlays' files
    (full size, thumbnail; relative to the page; None where not drawn)."""

    name: str
    entry: dict[str, Any]
    before: tuple[str, str] | None
    after: tuple[str, str] | None


def _num(x: Any, fmt: str = ".2f") -> str:
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "-"
    return format(x, fmt)


def _thumb(files: tuple[str, str] | None, alt: str) -> str:
    if files is None:
        return "-"
    full, thumb = (escape(f, quote=True) for f in files)
    return f'<a href="{full}"><img src="{thumb}" alt="{escape(alt)}"></a>'


def _image_table(rows: list[ImageRow], report: dict[str, Any]) -> str:
    facades = report.get("facades", {}).get("images", {})
    unc = report.get("uncertainty", {}).get("images", {})
    head = (
        "image",
        "map before (priors)",
        "map after",
        "status",
        "VP",
        "segments",
        "inlier corners",
        "residual RMS px (stage 2)",
        "bundle RMS px vertical / horizontal",
        "predicted sd px",
        "position sd m (major axis)",
        "message",
    )
    out = ["<table><tr>", *(f"<th>{h}</th>" for h in head), "</tr>"]
    for r in rows:
        e, f, u = r.entry, facades.get(r.name, {}), unc.get(r.name, {})
        brms = f.get("bundle_rms_px") or [None, None]
        ell = u.get("horizontal_ellipse_m") or [None]
        cls = (
            ' class="bad"'
            if e.get("status") != "registered"
            else (' class="warn"' if e.get("message") else "")
        )
        cells = (
            f'<td class="l">{escape(r.name)}</td>',
            f"<td>{_thumb(r.before, r.name + ' before')}</td>",
            f"<td>{_thumb(r.after, r.name + ' after')}</td>",
            f'<td class="l">{escape(str(e.get("status")))}</td>',
            f'<td class="l">{escape(str(e.get("vp_status") or "-"))}</td>',
            f"<td>{e.get('num_segments', '-')}</td>",
            f"<td>{e.get('num_inlier_corners', '-')}</td>",
            f"<td>{_num(e.get('residual_rms_px'))}</td>",
            f"<td>{_num(brms[0])} / {_num(brms[1])}</td>",
            f"<td>{_num(u.get('predicted_sd_px'))}</td>",
            f"<td>{_num(ell[0])}</td>",
            f'<td class="l">{escape(e.get("message") or "")}</td>',
        )
        out += [f"<tr{cls}>", *cells, "</tr>"]
    return "".join(out) + "</table>"


def _uncertainty_table(report: dict[str, Any]) -> str:
    unc = report.get("uncertainty")
    if not unc:
        return (
            "<p>No uncertainty in this run's report.json (no bundle, or written "
            "by an older obliq-colmap).</p>"
        )
    head = (
        "image (worst first)",
        "predicted sd px",
        "position sd m x / y / z",
        "ellipse m major / minor / angle deg",
        "rotation sd deg about camera x / y / z",
        "worst axis deg",
    )
    out = ["<table><tr>", *(f"<th>{h}</th>" for h in head), "</tr>"]
    for name, u in unc["images"].items():
        p = u.get("position_sd_m") or [None] * 3
        el = u.get("horizontal_ellipse_m") or [None] * 3
        rot = u.get("rotation_sd_deg") or [None] * 3
        cells = (
            f'<td class="l">{escape(name)}</td>',
            f"<td>{_num(u.get('predicted_sd_px'))}</td>",
            "<td>" + " / ".join(_num(v, ".3f") for v in p) + "</td>",
            f"<td>{_num(el[0], '.3f')} / {_num(el[1], '.3f')} / "
            f"{_num(el[2], '.0f')}</td>",
            "<td>" + " / ".join(_num(v, ".4f") for v in rot) + "</td>",
            f"<td>{_num(u.get('rotation_max_sd_deg'), '.4f')}</td>",
        )
        out += ["<tr>", *cells, "</tr>"]
    vf = unc.get("variance_factor")
    return (
        "".join(out)
        + "</table>"
        + f'<p class="note">Variance factor of the bundle: {_num(vf, ".3f")}. '
        + escape(unc.get("trust", TRUST_NOTE))
        + "</p>"
    )


def render_page(
    report: dict[str, Any],
    rows: list[ImageRow],
    histograms: list[str],
    plans: list[str],
    notes: list[str],
) -> str:
    """The whole HTML page (a str)."""
    bundle = report.get("bundle", {})
    summary = (
        f"<p>{escape(str(report.get('software', '')))}: registered "
        f"{report.get('num_registered', '?')} / {report.get('num_images', '?')} "
        f"images; images {escape(str(report.get('image_path', '')))}, map "
        f"{escape(str(report.get('cadastre_path', '')))}.</p>"
        + (f"<p>{escape(bundle['brief'])}</p>" if "brief" in bundle else "")
        + "".join(f'<p class="note">{escape(n)}</p>' for n in notes)
    )
    legend = (
        "<p class=\"note\">Overlays: the map's footprint edges at the image's "
        "ground height, drawn through the priors' camera and pose (red, "
        "before) and through the registered camera and pose (green, after). "
        "Click a thumbnail for the full-size JPEG. Rows in red: images left "
        "out; in yellow: written with a warning.</p>"
    )
    hist_note = (
        '<p class="note">Per-image residual RMS (one value per image): the '
        "registration's map corners against their image lines (stage 2), and "
        "the bundle's final vertical (map corners) and horizontal (facade "
        "edges) constraints; and the predicted sd of each image's "
        "projections.</p>"
    )
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        "<title>obliq-colmap registration report</title>"
        f"<style>{_CSS}</style></head><body>"
        "<h1>Registration report</h1>"
        + summary
        + "<h2>Images</h2>"
        + legend
        + _image_table(rows, report)
        + "<h2>Uncertainty</h2>"
        + _uncertainty_table(report)
        + "<h2>Residuals</h2>"
        + hist_note
        + '<div class="figs">'
        + "".join(histograms)
        + "</div><h2>Plan views</h2>"
        + "".join(f"<div>{p}</div>" for p in plans)
        + _CHECK
        + "</body></html>\n"
    )
