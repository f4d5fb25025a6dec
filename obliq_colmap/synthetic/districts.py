"""Block types beyond the mixed inner city: industrial halls and high-rise towers.

A district (``SceneOptions.district``) is a table of block-type probabilities
(:data:`~obliq_colmap.synthetic.options.DISTRICT_BLOCKS`); this module adds
the two block types the inner city lacks, as methods the city builder
inherits. Both work in the grid frame of the street layout, like the other
block types, and add mapped buildings through ``add_building``.

Why these two: an industrial hall has long, low, nearly windowless walls
(few vertical edges besides its corners, large flat roofs), a tower has long
vertical edges that reach far from its footprint in an oblique view and
occlude whole streets; each stresses a different part of the chain than the
mixed city does.
"""

from __future__ import annotations

import numpy as np
from shapely.geometry import Polygon


def _box(x0: float, y0: float, x1: float, y1: float) -> Polygon:
    return Polygon([(x0, y0), (x1, y0), (x1, y1), (x0, y1)])


class DistrictBlocks:
    """Block types of the industrial and high-rise districts (a mixin).

    The host class provides ``rng``, ``add_building``, ``floors``,
    ``_yard_clutter`` and ``_car`` (the city builder).
    """

    def _halls(self, x0: float, y0: float, x1: float, y1: float) -> None:
        """One to three halls along the block's long side, yards and parking between."""
        r = self.rng
        along_x = (x1 - x0) >= (y1 - y0)
        length, depth = (x1 - x0, y1 - y0) if along_x else (y1 - y0, x1 - x0)
        setback = r.uniform(5.0, 10.0)
        n_across = 2 if depth > 70 and r.uniform() < 0.6 else 1
        n_along = 2 if length > 80 and r.uniform() < 0.5 else 1
        gap = r.uniform(8.0, 14.0)
        span_a = (length - 2 * setback - (n_along - 1) * gap) / n_along
        span_d = (depth - 2 * setback - (n_across - 1) * gap) / n_across
        if span_a < 15 or span_d < 12:
            return
        for i in range(n_along):
            for j in range(n_across):
                a0 = setback + i * (span_a + gap)
                d0 = setback + j * (span_d + gap)
                # halls rarely fill their lot: leave a yard at one end
                a1 = a0 + span_a * r.uniform(0.75, 1.0)
                d1 = d0 + span_d * r.uniform(0.8, 1.0)
                if along_x:
                    poly = _box(x0 + a0, y0 + d0, x0 + a1, y0 + d1)
                else:
                    poly = _box(x0 + d0, y0 + a0, x0 + d1, y0 + a1)
                b = self.add_building(poly, self.floors(6.0, 12.0), shop_p=0.0)
                b.style = self._hall_style(b.height_m)
        self._parking(x0, y0, x1, y1, along_x, setback)

    def _hall_style(self, height: float) -> np.ndarray:
        """A band of high windows or none: one storey as tall as the hall."""
        r = self.rng
        win_h = r.uniform(0.8, 1.6)
        sill = min(r.uniform(2.5, 4.5), max(height - win_h - 0.8, 0.5))
        windows = 1.0 if r.uniform() < 0.7 else 0.0
        return np.array(
            [height + 5.0, height + 5.0, r.uniform(2.0, 4.0), win_h, sill,
             r.uniform(5.0, 9.0), 0.0, windows]
        )  # fmt: skip

    def _parking(self, x0, y0, x1, y1, along_x: bool, setback: float) -> None:
        """A row of cars parked along the front setback (unmapped clutter)."""
        r = self.rng
        if setback < 6.0 or r.uniform() < 0.3:
            return
        # the builder's _car(axis, off, s): axis 1 is a car along x at y = off
        off = (y0 if along_x else x0) + setback / 2
        start, end = (x0, x1) if along_x else (y0, y1)
        for s in np.arange(start + 6.0, end - 6.0, 6.2):
            if r.uniform() < 0.6:
                self._car(1 if along_x else 0, off, s, r.uniform(4.0, 4.8))

    def _towers(self, x0: float, y0: float, x1: float, y1: float) -> None:
        """One or two towers on a plaza with trees."""
        r = self.rng
        bw, bh = x1 - x0, y1 - y0
        n = 2 if max(bw, bh) > 80 and r.uniform() < 0.5 else 1
        placed: list[Polygon] = []
        for k in range(n):
            w, d = r.uniform(18.0, 32.0), r.uniform(18.0, 32.0)
            if n == 2 and bw >= bh:
                cx = x0 + (k + 0.5) * bw / 2 + r.uniform(-4, 4)
                cy = y0 + bh / 2 + r.uniform(-6, 6)
            elif n == 2:
                cx = x0 + bw / 2 + r.uniform(-6, 6)
                cy = y0 + (k + 0.5) * bh / 2 + r.uniform(-4, 4)
            else:
                cx = x0 + bw / 2 + r.uniform(-8, 8)
                cy = y0 + bh / 2 + r.uniform(-8, 8)
            poly = _box(cx - w / 2, cy - d / 2, cx + w / 2, cy + d / 2)
            inside = _box(x0 + 6, y0 + 6, x1 - 6, y1 - 6)
            if not poly.within(inside) or any(
                poly.buffer(6).intersects(p) for p in placed
            ):
                continue
            placed.append(poly)
            self.add_building(poly, self.floors(40.0, 100.0), shop_p=0.6)
        self._yard_clutter(
            x0 + 3, y0 + 3, x1 - 3, y1 - 3, n_trees=r.integers(2, 8), n_sheds=0
        )
