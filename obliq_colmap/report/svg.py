"""Figures of the report as inline SVG, drawn by hand: histograms
(:func:`histogram_svg`) and the plan view of the cameras over the map with
their horizontal error ellipses (:func:`plan_svg`).

Why not matplotlib: the page must render without network and without an
extra dependency on a clean install; a few rectangles, paths and ellipses are
all the figures need, and SVG stays sharp at any zoom.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from html import escape

import numpy as np

__all__ = ["PlanLayer", "histogram_svg", "nice_number", "plan_svg"]

_FONT = 'font-family="sans-serif" font-size="12"'


def nice_number(x: float) -> float:
    """The largest of 1, 2, 5 x 10^k not above ``x`` (> 0)."""
    k = math.floor(math.log10(x))
    for m in (5.0, 2.0, 1.0):
        if m * 10.0**k <= x:
            return m * 10.0**k
    return 10.0**k


def histogram_svg(
    values: np.ndarray, title: str, xlabel: str, width: int = 380, height: int = 220
) -> str:
    """A histogram of the finite (N,) ``values`` (10 bins) as one <svg>."""
    v = np.asarray(values, float)
    v = v[np.isfinite(v)]
    head = (
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}"'
        f' role="img" aria-label="{escape(title)}">'
        f'<text x="{width / 2}" y="16" text-anchor="middle" {_FONT}'
        f' font-weight="bold">{escape(title)}</text>'
    )
    if not len(v):
        return head + f'<text x="20" y="60" {_FONT}>no values</text></svg>'
    lo, hi = float(v.min()), float(v.max())
    if hi - lo < 1e-9:
        lo, hi = lo - 0.5, hi + 0.5
    counts, edges = np.histogram(v, bins=10, range=(lo, hi))
    x0, x1, y0, y1 = 40, width - 24, height - 40, 28  # room for the last tick
    sx = (x1 - x0) / (hi - lo)
    sy = (y0 - y1) / counts.max()
    bars = "".join(
        f'<rect x="{x0 + (a - lo) * sx:.1f}" y="{y0 - c * sy:.1f}"'
        f' width="{max((b - a) * sx - 1, 1):.1f}" height="{c * sy:.1f}"'
        ' fill="#4a7bb7"/>'
        for a, b, c in zip(edges[:-1], edges[1:], counts, strict=True)
        if c
    )
    ticks = "".join(
        f'<text x="{x0 + (t - lo) * sx:.1f}" y="{y0 + 14}" text-anchor="middle"'
        f" {_FONT}>{t:.3g}</text>"
        for t in np.linspace(lo, hi, 5)
    )
    return (
        head
        + bars
        + f'<line x1="{x0}" y1="{y0}" x2="{x1}" y2="{y0}" stroke="black"/>'
        + f'<line x1="{x0}" y1="{y0}" x2="{x0}" y2="{y1}" stroke="black"/>'
        + f'<text x="{x0 - 4}" y="{y1 + 10}" text-anchor="end" {_FONT}>'
        f"{counts.max()}</text>"
        + f'<text x="{x0 - 4}" y="{y0}" text-anchor="end" {_FONT}>0</text>'
        + ticks
        + f'<text x="{(x0 + x1) / 2}" y="{height - 6}" text-anchor="middle"'
        f" {_FONT}>{escape(xlabel)} (N = {len(v)})</text></svg>"
    )


@dataclass
class PlanLayer:
    """What :func:`plan_svg` draws over the footprints (model frame, m).

    Attributes
    ----------
    names : (K,) image names, labels of ``after``.
    before : (K, 2) priors' centres, NaN rows where absent.
    after : (K, 2) registered centres, NaN rows where not registered.
    ellipses : (K, 3) semi-major, semi-minor (m, 1 sd), angle (deg, counter-
        clockwise from east); NaN rows where unknown; None: no ellipses.
    """

    names: list[str]
    before: np.ndarray
    after: np.ndarray
    ellipses: np.ndarray | None = None


def _ellipse_scale(ellipses: np.ndarray, extent: float) -> float:
    """Magnification of the ellipses: the largest semi-major axis drawn at
    about 4 % of the plan's extent, a round number."""
    big = np.nanmax(ellipses[:, 0]) if np.any(np.isfinite(ellipses[:, 0])) else 0.0
    return nice_number(0.04 * extent / big) if big > 0 else 1.0


def plan_svg(
    polygons: list[np.ndarray], layer: PlanLayer, title: str, width: int = 900
) -> str:
    """Plan view (north up) of the (N_b, 2) footprint rings, the cameras'
    centres before (red) and after (green) registration joined by a line, and
    where given their horizontal 1-sd error ellipses, magnified by a stated
    round factor; a scale bar in metres."""
    pts = [p for p in polygons if len(p)] + [
        a[np.all(np.isfinite(a), axis=1)] for a in (layer.before, layer.after)
    ]
    allp = np.concatenate(pts) if pts else np.zeros((1, 2))
    lo, hi = allp.min(axis=0), allp.max(axis=0)
    extent = float(max(hi - lo)) or 1.0
    pad = 0.06 * extent
    lo, hi = lo - pad, hi + pad
    s = width / float(max(hi - lo))
    height = int(np.ceil((hi[1] - lo[1]) * s)) + 60

    def tx(xy: np.ndarray) -> np.ndarray:  # (N, 2) m -> (N, 2) SVG px, y down
        return np.column_stack([(xy[:, 0] - lo[0]) * s, (hi[1] - xy[:, 1]) * s + 30])

    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}"'
        f' role="img" aria-label="{escape(title)}">',
        f'<rect width="{width}" height="{height}" fill="white"/>',
        f'<text x="8" y="18" {_FONT} font-weight="bold">{escape(title)}</text>',
    ]
    d = "".join(
        "M" + "L".join(f"{x:.1f},{y:.1f}" for x, y in tx(p)) + "Z" for p in polygons
    )
    out.append(f'<path d="{d}" fill="#ddd" stroke="#888" stroke-width="0.6"/>')
    b, a = tx(layer.before), tx(layer.after)
    for k, name in enumerate(layer.names):
        if np.all(np.isfinite(b[k])) and np.all(np.isfinite(a[k])):
            out.append(
                f'<line x1="{b[k, 0]:.1f}" y1="{b[k, 1]:.1f}" x2="{a[k, 0]:.1f}"'
                f' y2="{a[k, 1]:.1f}" stroke="#999" stroke-dasharray="3,2"/>'
            )
        if np.all(np.isfinite(b[k])):
            out.append(
                f'<circle cx="{b[k, 0]:.1f}" cy="{b[k, 1]:.1f}" r="3" fill="#d62728">'
                f"<title>{escape(name)} (priors)</title></circle>"
            )
        if np.all(np.isfinite(a[k])):
            out.append(
                f'<circle cx="{a[k, 0]:.1f}" cy="{a[k, 1]:.1f}" r="3" fill="#2ca02c">'
                f"<title>{escape(name)}</title></circle>"
                f'<text x="{a[k, 0] + 5:.1f}" y="{a[k, 1] - 4:.1f}"'
                f' font-family="sans-serif" font-size="10">{escape(name)}</text>'
            )
    legend = "red: priors' centres, green: registered, dashed: the correction"
    if layer.ellipses is not None:
        mag = _ellipse_scale(layer.ellipses, extent)
        for k in range(len(layer.names)):
            e = layer.ellipses[k]
            if not (np.all(np.isfinite(e)) and np.all(np.isfinite(a[k]))):
                continue
            out.append(
                f'<ellipse cx="{a[k, 0]:.1f}" cy="{a[k, 1]:.1f}"'
                f' rx="{e[0] * mag * s:.1f}" ry="{e[1] * mag * s:.1f}"'
                f' transform="rotate({-e[2]:.1f} {a[k, 0]:.1f} {a[k, 1]:.1f})"'
                ' fill="none" stroke="#1f3f99" stroke-width="1.5"/>'
            )
        legend = (
            f"blue: horizontal 1-sd error ellipses, magnified x{mag:g}"
            f" (a 1 m sd draws as {mag:g} m on the map)"
        )
    bar = nice_number(0.2 * extent)
    y = height - 12
    out.append(
        f'<line x1="10" y1="{y}" x2="{10 + bar * s:.1f}" y2="{y}" stroke="black"'
        ' stroke-width="3"/>'
        f'<text x="{16 + bar * s:.1f}" y="{y + 4}" {_FONT}>{bar:g} m (map scale);'
        f" north up; {escape(legend)}</text></svg>"
    )
    return "".join(out)
