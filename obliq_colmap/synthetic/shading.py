"""Procedural materials: albedo of every rendered pixel from its 3D point.

The texture of a surface is a function of the surface id and the exact 3D
point seen in a pixel (from the perspective-correct depth), so textures are
evaluated per (super-)pixel without texture images. Facade layouts (window
columns, floors, shop fronts) use :func:`obliq_colmap.synthetic.city.window_columns`
and :func:`~obliq_colmap.synthetic.city.window_floors`, the same functions
that enumerate the true vertical texture edges.
"""

from __future__ import annotations

import numpy as np

from obliq_colmap.synthetic import city as C

_M1 = np.uint32(0x7FEB352D)
_M2 = np.uint32(0x846CA68B)
_MK = np.uint32(0x9E3779B1)


def _u32(k) -> np.ndarray:
    k = np.asarray(k)
    if k.dtype == np.uint32:
        return k
    if k.dtype.kind == "f":
        return k.astype(np.int32).view(np.uint32)
    return k.astype(np.int64).astype(np.uint32)


def hash01(*keys) -> np.ndarray:
    """Deterministic pseudo-random numbers in [0, 1) (float32) from integer keys.

    Keys (arrays or scalars, integers or integer-valued floats in the int32
    range) are folded by multiply-xor and finished with a 32-bit avalanche.
    """
    h = np.atleast_1d(_u32(keys[0])) * _MK  # arrays: uint32 wrap-around is intended
    for k in keys[1:]:
        h = (h ^ _u32(k)) * _MK + np.uint32(0x6B43A9B5)
    h = np.asarray(h, np.uint32)
    h = h ^ (h >> np.uint32(16))
    h = h * _M1
    h = h ^ (h >> np.uint32(15))
    h = h * _M2
    h = h ^ (h >> np.uint32(16))
    return (h >> np.uint32(8)).astype(np.float32) * np.float32(1.0 / (1 << 24))


def value_noise(x: np.ndarray, y: np.ndarray, scale: float, seed) -> np.ndarray:
    """Smooth value noise in [0, 1) with lattice spacing ``scale`` metres."""
    fx, fy = x / scale, y / scale
    ix, iy = np.floor(fx), np.floor(fy)
    tx, ty = (fx - ix).astype(np.float32), (fy - iy).astype(np.float32)
    tx = tx * tx * (3 - 2 * tx)
    ty = ty * ty * (3 - 2 * ty)
    ix, iy = _u32(ix), _u32(iy)
    one = np.uint32(1)
    a, b = hash01(ix, iy, seed), hash01(ix + one, iy, seed)
    c, d = hash01(ix, iy + one, seed), hash01(ix + one, iy + one, seed)
    return (a + (b - a) * tx) + ((c + (d - c) * tx) - (a + (b - a) * tx)) * ty


def _ground(city: C.City, P: np.ndarray, surf: np.ndarray) -> np.ndarray:
    L = city.layout
    c, s_ = np.float32(np.cos(L.theta)), np.float32(np.sin(L.theta))
    gx = c * P[:, 0] + s_ * P[:, 1]  # grid frame, float32 (sub-mm here)
    gy = -s_ * P[:, 0] + c * P[:, 1]
    n = len(P)
    out = np.empty((n, 3), np.float32)

    def nearest(lines, widths, coord):
        """Nearest street line: index, signed offset, half width; block index."""
        ss = np.searchsorted(lines, coord)
        k = np.clip(ss, 1, len(lines) - 1)
        left, right = coord - lines[k - 1], lines[k] - coord
        idx = np.where(left < right, k - 1, k)
        off = coord - lines[idx]
        return idx, off, widths[idx] / 2, np.clip(ss - 1, 0, len(lines) - 2)

    ix, offx, hwx, bx = nearest(L.xs, L.wx, gx)
    iy, offy, hwy, by = nearest(L.ys, L.wy, gy)
    ax, ay = np.abs(offx), np.abs(offy)
    in_x, in_y = ax < hwx, ay < hwy
    car_x, car_y = ax < hwx - C.SIDEWALK_M, ay < hwy - C.SIDEWALK_M
    road = car_x | car_y
    walk = (in_x | in_y) & ~road
    yard = ~(in_x | in_y)
    coarse = value_noise(gx, gy, 7.0, 11)
    fine = hash01(np.floor(gx / 0.3), np.floor(gy / 0.3), 5)
    # Asphalt, lane marks and zebra crossings.
    asphalt = 0.27 + 0.05 * coarse + 0.03 * fine
    lane_x = car_x & ~in_y & (ax < 0.08) & (np.mod(gy, 9.0) < 4.5)
    lane_y = car_y & ~in_x & (ay < 0.08) & (np.mod(gx, 9.0) < 4.5)
    zebra_here = hash01(ix, iy, 77) < 0.6
    zx = (
        car_x
        & (ay > hwy + 0.5)
        & (ay < hwy + 3.5)
        & (np.mod(offx, 1.0) < 0.5)
        & zebra_here
    )
    zy = (
        car_y
        & (ax > hwx + 0.5)
        & (ax < hwx + 3.5)
        & (np.mod(offy, 1.0) < 0.5)
        & zebra_here
    )
    mark = lane_x | lane_y | zx | zy
    val = np.where(mark, 0.82 + 0.05 * fine, asphalt)
    out[:] = val[:, None] * np.array([1.0, 1.0, 1.04], np.float32)
    # Sidewalks: paving slabs and a kerb.
    slab = (np.mod(gx, 0.6) < 0.04) | (np.mod(gy, 0.6) < 0.04)
    kerb = (np.abs(ax - (hwx - C.SIDEWALK_M)) < 0.15) | (
        np.abs(ay - (hwy - C.SIDEWALK_M)) < 0.15
    )
    wv = np.where(kerb, 0.72, np.where(slab, 0.5, 0.6 + 0.04 * coarse + 0.03 * fine))
    out[walk] = wv[walk, None] * np.array([1.0, 0.98, 0.94], np.float32)
    # Yards: grass or paving by block.
    kind = city.layout.block_kind[
        np.clip(by, 0, L.block_kind.shape[0] - 1),
        np.clip(bx, 0, L.block_kind.shape[1] - 1),
    ]
    grass = yard & (kind == 1)
    paved = yard & (kind == 0)
    gn = value_noise(gx, gy, 3.0, 21)
    out[grass] = (
        np.array([0.30, 0.42, 0.18], np.float32)
        * (0.75 + 0.35 * gn[grass] + 0.1 * fine[grass])[:, None]
    )
    out[paved] = (
        np.array([0.55, 0.53, 0.49], np.float32)
        * (0.85 + 0.2 * coarse[paved] + 0.05 * fine[paved])[:, None]
    )
    return out


def _wall(city: C.City, P: np.ndarray, surf: np.ndarray) -> np.ndarray:
    org = city.surf_origin[surf]
    U = city.surf_u[surf]
    u = ((P[:, 0] - org[:, 0]) * U[:, 0] + (P[:, 1] - org[:, 1]) * U[:, 1]).astype(
        np.float32
    )
    v = (P[:, 2] - org[:, 2]).astype(np.float32)
    st = city.surf_style[surf].astype(np.float32)
    floor_h, ground_h, win_w, win_h, sill, col, shop, _ = st.T
    # Gable triangles and other walls without windows carry a zero style.
    floor_h = np.where(floor_h > 0, floor_h, np.float32(3.0))
    col = np.where(col > 0, col, np.float32(3.0))
    length = city.surf_length[surf].astype(np.float32)
    height = city.surf_height[surf].astype(np.float32)
    base = city.surf_color[surf]
    frame_c = city.surf_color2[surf]
    seed = city.surf_seed[surf]
    n_cols, u0 = C.window_columns(length, st)
    n_up = C.window_floors(height, st)
    k = np.clip(
        np.round((u - u0) / np.maximum(col, 1e-3)), 0, np.maximum(n_cols - 1, 0)
    )
    du = u - (u0 + k * col)
    in_col = (n_cols > 0) & (np.abs(du) < win_w / 2)
    fi = np.floor((v - ground_h) / floor_h)
    dv = v - ground_h - fi * floor_h - sill
    upper = (fi >= 0) & (fi < n_up) & (dv >= 0) & (dv < win_h)
    is_shop = shop > 0
    g_dv = v - sill
    ground_win = ~is_shop & (v < ground_h) & (g_dv >= 0) & (g_dv < win_h)
    dvw = np.where(upper, dv, g_dv)
    window = in_col & (upper | ground_win)
    frame = window & (
        (np.abs(du) > win_w / 2 - C.FRAME_M)
        | (dvw < C.FRAME_M)
        | (dvw > win_h - C.FRAME_M)
    )
    # Facade: weathering noise, plinth, floor bands, cornice.
    noise = value_noise(u, v, 1.3, seed)
    col_out = base * (0.93 + 0.1 * noise)[:, None]
    rel = v - ground_h - np.floor((v - ground_h) / floor_h) * floor_h
    band = (
        (v >= ground_h - 0.01)
        & (rel < 0.22)
        & (np.floor((v - ground_h) / floor_h) <= n_up)
        & (st[:, 7] > 0)
        & (v < height - 0.5)
    )
    col_out = np.where(band[:, None], col_out * 0.8, col_out)
    col_out = np.where((v < 0.45)[:, None], col_out * 0.68, col_out)
    col_out = np.where(
        ((v > height - 0.35) & (v < height + 0.05))[:, None], col_out * 0.78, col_out
    )
    # Shop fronts on the ground floor.
    shop_zone = (
        is_shop
        & (v < ground_h)
        & (u > C.WINDOW_MARGIN_M)
        & (u < length - C.WINDOW_MARGIN_M)
    )
    kp = np.clip(
        np.round((u - u0) / np.maximum(col, 1e-3) - 0.5), 0, np.maximum(n_cols - 2, 0)
    )
    pillar = (n_cols > 1) & (np.abs(u - (u0 + col * (kp + 0.5))) < 0.25)
    glass_shop = shop_zone & ~pillar & (v > 0.5) & (v < ground_h - 0.6)
    sign = shop_zone & ~pillar & (v >= ground_h - 0.6) & (v < ground_h - 0.1)
    h1 = hash01(seed, kp, 3)
    sign_col = np.stack(
        [
            0.3 + 0.6 * h1,
            0.3 + 0.6 * hash01(seed, kp, 4),
            0.3 + 0.6 * hash01(seed, kp, 5),
        ],
        1,
    )
    col_out = np.where(sign[:, None], sign_col, col_out)
    glass_c = (0.08 + 0.1 * hash01(seed, np.floor(u / 1.5), 9))[:, None] * np.array(
        [1.0, 1.1, 1.25], np.float32
    )
    col_out = np.where(glass_shop[:, None], glass_c, col_out)
    # Windows: dark glass with some reflections, light or dark frames.
    wr = hash01(seed, k, fi)
    gl = (0.12 + 0.22 * wr * wr)[:, None] * np.array([0.95, 1.05, 1.2], np.float32)
    col_out = np.where(window[:, None], np.where(frame[:, None], frame_c, gl), col_out)
    return col_out.astype(np.float32)


def _roof_pitched(city, P, surf):
    org = city.surf_origin[surf]
    U, V = city.surf_u[surf], city.surf_v[surf]
    d = P - org
    u = np.einsum("ij,ij->i", d, U).astype(np.float32)
    v = np.einsum("ij,ij->i", d, V).astype(np.float32)
    seed = city.surf_seed[surf]
    row = np.floor(v / 0.34)
    tile = hash01(np.floor(u / 0.26 + 0.5 * np.mod(row, 2)), row, seed)
    c = (
        city.surf_color[surf]
        * (0.88 + 0.12 * tile + 0.1 * value_noise(u, v, 4.0, seed))[:, None]
    )
    gap = np.mod(v, 0.34) < 0.05
    return np.where(gap[:, None], c * 0.72, c).astype(np.float32)


def _roof_flat(city, P, surf):
    seed = city.surf_seed[surf]
    n = value_noise(P[:, 0], P[:, 1], 2.5, seed) * 0.6 + 0.4 * hash01(
        np.floor(P[:, 0] / 0.25), np.floor(P[:, 1] / 0.25), seed
    )
    return (city.surf_color[surf] * (0.85 + 0.25 * n)[:, None]).astype(np.float32)


def _plain(city, P, surf):
    seed = city.surf_seed[surf]
    n = value_noise(P[:, 0] + P[:, 2], P[:, 1] - P[:, 2], 0.8, seed)
    return (city.surf_color[surf] * (0.92 + 0.12 * n)[:, None]).astype(np.float32)


def _tree(city, P, surf):
    seed = city.surf_seed[surf]
    n1 = value_noise(P[:, 0] + 0.7 * P[:, 2], P[:, 1] - 0.7 * P[:, 2], 0.6, seed)
    n2 = value_noise(P[:, 0] - 0.5 * P[:, 2], P[:, 1] + 0.4 * P[:, 2], 1.7, seed + 1)
    return (city.surf_color[surf] * (0.55 + 0.45 * n1 + 0.35 * n2)[:, None]).astype(
        np.float32
    )


def _box(city, P, surf, normal):
    """Cars (glass band, dark bottom) and sheds / roof boxes (darker top)."""
    org = city.surf_origin[surf]
    h = (P[:, 2] - org[:, 2]).astype(np.float32)
    H = city.surf_height[surf].astype(np.float32)
    mat = city.surf_material[surf]
    base = city.surf_color[surf]
    other = city.surf_color2[surf]
    top = normal[:, 2] > 0.9
    car = mat == C.CAR
    glass = car & ~top & (h > 0.55 * H) & (h < 0.9 * H)
    dark = car & (h < 0.3)
    out = np.where((top & ~car)[:, None], other, base)
    out = np.where(glass[:, None], other, out)
    out = np.where(dark[:, None], base * 0.3, out)
    return out.astype(np.float32)


def albedo(city: C.City, P: np.ndarray, face_id: np.ndarray) -> np.ndarray:
    """Albedo (N, 3) float32 in [0, 1] of points P (N, 3) on faces ``face_id``."""
    surf = city.face_surface[face_id]
    mat = city.surf_material[surf]
    out = np.zeros((len(P), 3), np.float32)
    for m in np.unique(mat):
        idx = np.nonzero(mat == m)[0]
        Pm, sm = P[idx], surf[idx]
        if m == C.GROUND:
            out[idx] = _ground(city, Pm, sm)
        elif m == C.WALL:
            out[idx] = _wall(city, Pm, sm)
        elif m == C.ROOF_PITCHED:
            out[idx] = _roof_pitched(city, Pm, sm)
        elif m == C.ROOF_FLAT:
            out[idx] = _roof_flat(city, Pm, sm)
        elif m == C.TREE:
            out[idx] = _tree(city, Pm, sm)
        elif m == C.FLAT:
            out[idx] = city.surf_color[sm]
        elif m in (C.CAR, C.SHED):
            out[idx] = _box(city, Pm, sm, city.face_normal[face_id[idx]])
        else:
            out[idx] = _plain(city, Pm, sm)
    return out


def sun_direction(azimuth_deg: float, elevation_deg: float) -> np.ndarray:
    """(3,) unit vector towards the sun (azimuth clockwise from north)."""
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    return np.array([np.sin(a) * np.cos(e), np.cos(a) * np.cos(e), np.sin(e)])


def shade(
    city: C.City, P: np.ndarray, face_id: np.ndarray, sun: np.ndarray
) -> np.ndarray:
    """Lit colour (N, 3) float32: albedo x (sky + wrapped Lambert towards the sun).

    The wrapped diffuse term ``max(0, (n . sun + 0.6) / 1.6)`` stands in for the
    anisotropic sky: walls facing away from the sun still differ by direction,
    so building corners keep some contrast in every viewing direction.
    """
    n = city.face_normal[face_id].astype(np.float32)
    lam = np.clip((n @ sun.astype(np.float32) + 0.6) / 1.6, 0.0, None)
    sky = 0.42 + 0.08 * n[:, 2]
    return albedo(city, P, face_id) * (sky + 0.65 * lam)[:, None]
