"""The painted surface: canvas weave, cracks, colour areas, brush-stroke ridges, primer spots and
the protrusions of several shapes.

Part of :mod:`uvps.testing.synthetic`, which exposes every public name; import from there.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from ..errors import UVPSInputError
from .synthetic_spec import (
    DARK_AREA_COLOURS,
    LIGHT_AREA_COLOURS,
    PRIMER_COLOUR,
    PROTRUSION_COLOUR,
    PROTRUSION_GEOMETRIES,
    PROTRUSION_KINDS,
    _UM2_PER_CM2,
)
from .synthetic_render import _normalised, _substream


def _weave(spec, theta, xu, yu):
    """Plain weave (um) of one or several scales: ``A sin(2 pi u / P) sin(2 pi v / P)`` in axes
    turned by ``theta``; further scales turned a little more, with random phases."""
    periods, amps = _weave_scales(spec)
    u = xu * math.cos(theta) + yu * math.sin(theta)
    v = -xu * math.sin(theta) + yu * math.cos(theta)
    k = 2 * np.pi / periods[0]
    height = amps[0] * np.sin(k * u) * np.sin(k * v)
    if len(periods) > 1:
        rng = _substream(spec.seed, "weave")
        for period, amp in zip(periods[1:], amps[1:]):
            th = theta + rng.uniform(-0.05, 0.05)
            ph = rng.uniform(0, 2 * np.pi, 2)
            u = xu * math.cos(th) + yu * math.sin(th)
            v = -xu * math.sin(th) + yu * math.cos(th)
            k = 2 * np.pi / period
            height = height + amp * np.sin(k * u + ph[0]) * np.sin(k * v + ph[1])
    return height


def _weave_scales(spec):
    """Weave periods and amplitudes as equal-length lists of floats."""
    periods = [float(p) for p in np.atleast_1d(spec.weave_period_um)]
    amps = [float(a) for a in np.atleast_1d(spec.weave_amplitude_um)]
    if len(amps) == 1:
        amps = amps * len(periods)
    if not periods or len(amps) != len(periods):
        raise UVPSInputError(f"weave_amplitude_um must be one number or one per weave period "
                             f"({len(periods)}); got {spec.weave_amplitude_um!r}")
    if any(not p > 0 for p in periods) or any(not a >= 0 for a in amps):
        raise UVPSInputError(f"weave_period_um must be > 0 and weave_amplitude_um >= 0; got "
                             f"{spec.weave_period_um!r}, {spec.weave_amplitude_um!r}")
    return periods, amps


def _crack_seeds(rng, shape, spacing_px):
    """Seeds of the crack network (rows, cols) and each one's spacing: dart throwing, every
    seed with its own spacing drawn in ``spacing_px`` = (low, high), over the image and a
    border one high-spacing wide (so the border cells are whole)."""
    m, n = shape
    lo, hi = spacing_px
    box_lo, box_hi = np.array([-hi, -hi]), np.array([m + hi, n + hi])
    seeds = np.empty((0, 2))
    radii = np.empty(0)
    failures = 0
    while failures < 300:
        cand = rng.uniform(box_lo, box_hi)
        r = rng.uniform(lo, hi)
        if seeds.size and np.any(np.hypot(*(seeds - cand).T) < 0.5 * (radii + r)):
            failures += 1
            continue
        seeds = np.vstack([seeds, cand])
        radii = np.append(radii, r)
        failures = 0
    return seeds, radii


def _cracks(rng, shape, px, cupping_um, cell_mm):
    """Craquelure: cupped paint islands between narrow crack grooves.

    Returns the height layer (um, (M, N)), the groove mask (M, N) bool and the parameters.
    The islands are Voronoi cells of seeds ``cell_mm`` apart, in coordinates warped by smooth
    noise so the cracks wander. At distance ``e`` from the edge of its cell (the nearest
    bisector with a neighbouring seed), island i is ``c_i * (1 - e / R_i)^2`` high (``c_i`` up
    to ``cupping_um``, ``R_i`` half its spacing), and the groove brings every crack down to a
    common ``-cupping_um / 2`` over a gaussian of 15-30 um 1/e half-width (25-50 um wide at
    half depth).
    """

    m, n = shape
    lo, hi = (c * 1000.0 / px for c in cell_mm)
    seeds, spacing = _crack_seeds(rng, shape, (lo, hi))
    amp = 0.08 * lo
    sigma = max(lo / 4.0, 1.0)
    warp = [amp * _normalised(ndimage.gaussian_filter(rng.standard_normal(shape), sigma))
            for _ in range(2)]
    rr = (np.arange(m, dtype=np.float32)[:, None] + warp[0]).ravel()
    cc = (np.arange(n, dtype=np.float32)[None, :] + warp[1]).ravel()
    # distance to the cell's edge: to the nearest bisector with one of the next seeds (exact
    # for a convex cell whose neighbours are among them)
    dist, idx = cKDTree(seeds).query(np.stack([rr, cc], axis=1), k=min(6, len(seeds)))
    d0 = dist[:, 0] ** 2
    twice_gap = 2.0 * np.hypot(*(seeds[:, None, :] - seeds[None, :, :]).transpose(2, 0, 1))
    edge = np.full(d0.shape, np.inf)
    for j in range(1, idx.shape[1]):
        np.minimum(edge, (dist[:, j] ** 2 - d0) / twice_gap[idx[:, 0], idx[:, j]], out=edge)
    edge = edge.reshape(shape)                                                  # px
    cup = cupping_um * rng.uniform(0.4, 1.0, len(seeds))
    half = 0.5 * spacing
    own = idx[:, 0].reshape(shape)
    dish = cup[own] * np.clip(1.0 - edge / half[own], 0.0, None) ** 2
    groove_w = rng.uniform(15.0, 30.0) / px            # gaussian 1/e half-width (FWHM 25-50 um)
    depth = 0.5 * cupping_um
    g = np.exp(-(edge / groove_w) ** 2)
    layer = dish * (1.0 - g) - depth * g
    mask = edge < max(0.83 * groove_w, 0.71)       # below half depth, at least a pixel wide
    in_view = np.all((seeds > -0.5) & (seeds < np.array([m, n]) - 0.5), axis=1)
    info = {"cupping_um": float(cupping_um), "cell_mm": list(cell_mm),
            "n_islands": int(np.unique(own).size), "n_seeds_in_view": int(in_view.sum()),
            "groove_depth_um": depth, "groove_half_width_um": float(groove_w * px),
            "groove_fraction": float(mask.mean())}
    return layer, mask, info


# --------------------------------------------------------------------------------------------
# Scene
# --------------------------------------------------------------------------------------------


def _smooth_warp(rng, shape, amplitude, n_waves=4):
    """A smooth random displacement (pixels): a sum of a few long plane waves."""
    m, n = shape
    r = np.arange(m)[:, None]
    c = np.arange(n)[None, :]
    out = np.zeros(shape)
    size = max(m, n)
    for _ in range(n_waves):
        wavelength = rng.uniform(0.25, 0.8) * size
        theta = rng.uniform(0, np.pi)
        k = 2 * np.pi / wavelength
        out += np.sin(k * (np.cos(theta) * c + np.sin(theta) * r) + rng.uniform(0, 2 * np.pi))
    return out * amplitude / math.sqrt(n_waves)


def _colour_areas(rng, shape, n_regions):
    """Irregular colour areas: Voronoi cells of random seeds in warped coordinates."""
    m, n = shape
    seeds = []
    min_d = 0.6 * math.sqrt(m * n / n_regions)
    for _ in range(2000):
        if len(seeds) == n_regions:
            break
        s = rng.uniform([0.05 * m, 0.05 * n], [0.95 * m, 0.95 * n])
        if all(np.hypot(*(s - t)) > min_d for t in seeds):
            seeds.append(s)
        else:
            min_d *= 0.995
    amp = 0.08 * min(m, n)
    rr = np.arange(m, dtype=np.float32)[:, None] + _smooth_warp(rng, shape, amp)
    cc = np.arange(n, dtype=np.float32)[None, :] + _smooth_warp(rng, shape, amp)
    best = np.full(shape, np.inf, dtype=np.float32)
    labels = np.zeros(shape, dtype=np.int32)
    for i, (sr, sc) in enumerate(seeds):
        d = (rr - sr) ** 2 + (cc - sc) ** 2
        closer = d < best
        best[closer] = d[closer]
        labels[closer] = i + 1
    # Relabel 1..R in case a warped cell vanished.
    present = np.unique(labels)
    lut = np.zeros(labels.max() + 1, dtype=np.int32)
    lut[present] = np.arange(1, len(present) + 1)
    return lut[labels]


def _region_palette(rng, n_regions):
    """Names, light flags and colours for R areas (2-5 light, 1-3 dark)."""
    n_dark = int(rng.integers(max(1, n_regions - len(LIGHT_AREA_COLOURS)),
                              min(len(DARK_AREA_COLOURS), n_regions - 1) + 1))
    light = list(rng.permutation(list(LIGHT_AREA_COLOURS)))[: n_regions - n_dark]
    dark = list(rng.permutation(list(DARK_AREA_COLOURS)))[:n_dark]
    names = light + dark
    order = rng.permutation(n_regions)
    names = [str(names[i]) for i in order]
    is_light = [nm in LIGHT_AREA_COLOURS for nm in names]
    colours = np.array([{**LIGHT_AREA_COLOURS, **DARK_AREA_COLOURS}[nm] for nm in names])
    return names, is_light, colours


@dataclass
class _Impasto:
    """The impasto options of :class:`SyntheticSpec` and their own random stream."""

    blunt: float = 0.0
    ripple: tuple = (0.0, 0.0)
    groove_um: tuple = (0.0, 0.0)
    crossing: float = 0.0
    rng: Optional[np.random.Generator] = None

    @classmethod
    def of(cls, spec):
        imp = cls(spec.ridge_blunt_fraction, tuple(spec.ridge_ripple), tuple(spec.ridge_groove_um),
                  spec.ridge_crossing_fraction)
        if imp.blunt > 0 or imp.ripple[1] > 0 or imp.groove_um[1] > 0 or imp.crossing > 0:
            imp.rng = _substream(spec.seed, "impasto")
        return imp


def _stroke_relief(imp, tn, dist, prof, length, width, h, px):
    """One stroke's height (um) in its box: ``tn`` the position along it (0..1) of the nearest
    centreline pixel, ``dist`` the distance to it (px), ``prof`` the cross profile (0..1).
    Without impasto: ``h prof`` tapered by a smoothstep over 15 % of the length at both ends.
    Returns (height, its shape relative to ``h`` clipped to 1, which tints the albedo)."""
    def smooth(x):
        x = np.clip(x, 0, 1)
        return x * x * (3 - 2 * x)
    if imp.rng is None:
        shape_k = prof * smooth(np.minimum(tn, 1 - tn) / 0.15)
        return h * shape_k, shape_k
    r = imp.rng
    mound = np.ones_like(tn)
    ends = []
    for s_end in (tn * length, (1 - tn) * length):          # px from each end along the path
        if r.random() < imp.blunt:
            # full height to a rounded end (the cap), and the paint piled where the brush lifts
            ends.append(np.ones_like(tn))
            pile = r.uniform(0.2, 0.5)
            mound = mound + pile * np.exp(-((s_end - 0.5 * width) / (0.5 * width)) ** 2)
        else:
            ends.append(smooth(s_end / (0.15 * length)))
    rel = np.minimum(*ends) * mound
    amp = r.uniform(*imp.ripple)
    if amp > 0:
        wave = r.uniform(200.0, 800.0) / px
        rel = rel * (1 + amp * np.sin(2 * np.pi * tn * length / wave + r.uniform(0, 2 * np.pi)))
    z = h * prof * rel
    depth = r.uniform(*imp.groove_um)
    if depth > 0:
        period = r.uniform(40.0, 120.0) / px
        grooves = 0.5 * (1 + np.cos(2 * np.pi * dist / period + r.uniform(0, 2 * np.pi)))
        z = np.maximum(z - depth * grooves * np.minimum(3 * prof, 1) * np.minimum(rel, 1), 0)
    return z, np.minimum(z / h, 1)


def _ridges(rng, shape, px, count, albedo_factor, occupied, *, width_um=(100.0, 300.0),
            height_um=(5.0, 20.0), impasto=None):
    """Brush-stroke ridges: curved, several mm long, ``width_um`` wide, ``height_um`` high.

    Distance to each stroke's centreline comes from ``scipy.ndimage.distance_transform_edt``
    (with the indices of the nearest centreline pixel, to taper the stroke ends);
    ``impasto`` (:class:`_Impasto`) adds blunt ends, ripples, bristle grooves and crossings.
    """
    m, n = shape
    imp = impasto if impasto is not None else _Impasto()
    layer = np.zeros(shape)
    base_angle = rng.uniform(0, np.pi)
    for _ in range(count):
        length = rng.uniform(3000.0, 10000.0) / px           # pixels
        width = rng.uniform(*width_um) / px
        h = rng.uniform(*height_um)
        angle = base_angle + rng.uniform(-0.5, 0.5)
        crossing = imp.rng is not None and imp.rng.random() < imp.crossing
        if crossing:
            angle = imp.rng.uniform(0, np.pi)
        start = rng.uniform([0, 0], [m, n])
        direc = np.array([np.sin(angle), np.cos(angle)])
        end = start + length * direc
        bend = rng.uniform(-0.15, 0.15) * length
        ctrl = (start + end) / 2 + bend * np.array([-direc[1], direc[0]])
        t = np.linspace(0, 1, int(2 * length) + 2)[:, None]
        path = (1 - t) ** 2 * start + 2 * t * (1 - t) * ctrl + t ** 2 * end
        pad = int(width) + 2
        r0 = max(int(path[:, 0].min()) - pad, 0)
        r1 = min(int(path[:, 0].max()) + pad + 1, m)
        c0 = max(int(path[:, 1].min()) - pad, 0)
        c1 = min(int(path[:, 1].max()) + pad + 1, n)
        if r1 - r0 < 2 or c1 - c0 < 2:
            continue
        pr = np.rint(path[:, 0]).astype(int) - r0
        pc = np.rint(path[:, 1]).astype(int) - c0
        inside = (pr >= 0) & (pr < r1 - r0) & (pc >= 0) & (pc < c1 - c0)
        if not inside.any():
            continue
        line = np.ones((r1 - r0, c1 - c0), dtype=bool)
        tval = np.zeros(line.shape)
        line[pr[inside], pc[inside]] = False
        tval[pr[inside], pc[inside]] = t[inside, 0]
        dist, (ir, ic) = ndimage.distance_transform_edt(line, return_indices=True)
        half = width / 2
        prof = np.where(dist < half, 0.5 * (1 + np.cos(np.pi * dist / half)), 0.0)
        tn = tval[ir, ic]
        z, shape_k = _stroke_relief(imp, tn, dist, prof, length, width, h, px)
        if crossing:
            layer[r0:r1, c0:c1] += z                         # laid over dry paint
        else:
            layer[r0:r1, c0:c1] = np.maximum(layer[r0:r1, c0:c1], z)
        albedo_factor[r0:r1, c0:c1] *= 1 + rng.uniform(-0.06, 0.04) * shape_k
    occupied |= layer > 1.0
    return layer


def _primer_spots(rng, shape, px, count, albedo, occupied):
    """Flat whitish primer spots (paint missing): albedo toward the primer colour, height 0 to
    3 um below the paint. Returns the height layer (<= 0)."""
    m, n = shape
    layer = np.zeros(shape)
    primer = np.array(PRIMER_COLOUR)[: albedo.shape[2]]
    for _ in range(count):
        w = rng.uniform(100.0, 400.0) / px
        aspect = rng.uniform(1.0, 1.6)
        a, b = w / 2 * math.sqrt(aspect), w / 2 / math.sqrt(aspect)
        phi = rng.uniform(0, np.pi)
        cr, cc = rng.uniform([a + 2, a + 2], [m - a - 2, n - a - 2])
        r0, r1 = int(cr - a - 2), int(cr + a + 3)
        c0, c1 = int(cc - a - 2), int(cc + a + 3)
        rows = np.arange(r0, r1)[:, None] - cr
        cols = np.arange(c0, c1)[None, :] - cc
        u = cols * np.cos(phi) + rows * np.sin(phi)
        v = -cols * np.sin(phi) + rows * np.cos(phi)
        theta = np.arctan2(v, u)
        wobble = 1 + sum(rng.uniform(-0.08, 0.08) * np.cos(j * theta + rng.uniform(0, 6.3))
                         for j in (2, 3, 5))
        rho = np.sqrt((u / a) ** 2 + (v / b) ** 2) / wobble
        wgt = np.clip((1 - rho) * a / 1.5, 0, 1)
        depth = rng.uniform(0.0, 3.0)
        layer[r0:r1, c0:c1] = np.minimum(layer[r0:r1, c0:c1], -depth * wgt)
        sub = albedo[r0:r1, c0:c1]
        sub[:] = sub * (1 - wgt[..., None]) + primer * rng.uniform(0.95, 1.05) * wgt[..., None]
        occupied[r0:r1, c0:c1] |= rho < 1.3
    return layer


def _protrusion_widths(rng, count, width_range, median_um=150.0):
    """Widths (um) skewed to 100-200 um: log-normal (median ``median_um``, 150 um by default,
    sigma 0.45) truncated to ``width_range``."""
    lo, hi = width_range
    median = min(max(median_um, lo), hi)
    out = np.empty(0)
    while out.size < count:
        w = rng.lognormal(math.log(median), 0.45, 2 * count + 10)
        out = np.concatenate([out, w[(w >= lo) & (w <= hi)]])
    return out[:count]


def _dome_profile(rho, gamma, crater):
    """Normalised dome height at elliptical radius rho (0 outside the footprint rho >= 1)."""
    f = np.where(rho < 1, np.clip(1 - rho * rho, 0, None) ** gamma, 0.0)
    if crater is not None:
        depth, rc = crater
        inner = np.clip(1 - (rho / rc) ** 2, 0, None) ** 2
        f = f - depth * inner
    return f


def _profile(rho, gamma, crater, plateau):
    """Dome/crater profile, or a mesa: flat out to ``plateau``, then a smoothstep to rho = 1."""
    if plateau is None:
        return _dome_profile(rho, gamma, crater)
    t = np.clip((1 - rho) / (1 - plateau), 0, 1)
    return t * t * (3 - 2 * t)


class _Shapes:
    """Draws of :attr:`SyntheticSpec.protrusion_shapes` (kinds, outlines, cluster members)
    from their own random stream."""

    def __init__(self, spec):
        weights = spec.protrusion_shapes
        self.rng = _substream(spec.seed, "protrusion shapes")
        self.kinds = [k for k in PROTRUSION_KINDS if weights.get(k, 0) > 0]
        p = np.array([float(weights[k]) for k in self.kinds])
        self.p = p / p.sum()
        geo = np.array([float(weights.get(k, 0.0)) for k in PROTRUSION_GEOMETRIES])
        self.geo_p = geo / geo.sum() if geo.sum() > 0 else np.array([1.0, 0, 0, 0])

    def kind(self):
        return self.kinds[self.rng.choice(len(self.kinds), p=self.p)]

    def geometry(self):
        return PROTRUSION_GEOMETRIES[self.rng.choice(len(PROTRUSION_GEOMETRIES), p=self.geo_p)]

    def wobble(self):
        """A lumpy outline: harmonics 2, 3, 5 of 8-20 %, 5-12 % and 2-6 %; the footprint scale
        that keeps the area (mean of w^2 = 1 + sum amp^2 / 2) and the outline's reach (max w)."""
        amps = (self.rng.uniform([0.08, 0.05, 0.02], [0.2, 0.12, 0.06])
                * self.rng.choice([-1.0, 1.0], 3))
        phases = self.rng.uniform(0, 2 * np.pi, 3)
        theta = np.linspace(0, 2 * np.pi, 721)
        w = 1 + sum(a * np.cos(j * theta + ph) for a, j, ph in zip(amps, (2, 3, 5), phases))
        return {"amps": amps, "phases": phases,
                "scale": 1.0 / math.sqrt(1.0 + float(np.sum(amps ** 2)) / 2.0),
                "reach": float(w.max())}


_TABLE_KEYS = ("y_px", "x_px", "width_um", "height_um", "crater", "weak", "region", "aspect",
               "angle_deg", "shape", "cluster", "dark")


def _protrusions(rng, spec, labels, region_light, px, height, albedo, occupied, ridge_mask=None):
    """Place non-overlapping protrusions per colour area and add them to height and albedo
    (``on_stroke_fraction`` of them on or against a stroke of ``ridge_mask``)."""
    placer = _Placer(rng, spec, labels, px, height, albedo, occupied, ridge_mask)
    for reg in range(1, labels.max() + 1):
        placer.place_in_region(reg, region_light[reg - 1])
    return placer.columns()


class _Placer:
    """The state of placing protrusions area by area: the height and albedo they are stamped
    into, the pixels they (and the strokes, spots) occupy, and the table of what was placed.

    The main stream ``rng`` draws in one fixed order (count, widths, then per protrusion its
    aspect, tries, look); the shapes and the on-stroke choice come from their own streams so
    that switching them on leaves the main stream's draws as they were."""

    def __init__(self, rng, spec, labels, px, height, albedo, occupied, ridge_mask):
        self.rng, self.spec, self.labels, self.px = rng, spec, labels, px
        self.height, self.albedo, self.occupied, self.ridge_mask = height, albedo, occupied, ridge_mask
        m, n = self.shape = labels.shape
        self.on_f = spec.on_stroke_fraction if ridge_mask is not None and ridge_mask.any() else 0.0
        if self.on_f > 0:
            self.srng = _substream(spec.seed, "on stroke")
            self.near_stroke = ndimage.binary_dilation(ridge_mask, iterations=4).ravel()
            self.prot_occ = np.zeros((m, n), bool)
        self.table = {key: [] for key in _TABLE_KEYS + (("on_stroke",) if self.on_f > 0 else ())}
        self.colour = np.array(PROTRUSION_COLOUR)[: albedo.shape[2]]
        self.flat = labels.ravel()
        self.shapes = None if spec.protrusion_shapes is None else _Shapes(spec)
        self.scratch = (np.zeros((m, n)) if self.shapes is not None and "cluster" in self.shapes.kinds
                        else None)
        self.n_clusters = 0
        self.on_now = False

    def clip_height(self, h):
        """A drawn height within ``spec.height_um`` (when set)."""
        h_range = self.spec.height_um
        return h if h_range is None else min(max(h, h_range[0]), h_range[1])

    def stamp(self, cr, cc, a, b, margin, phi, h_dome, gamma, crater, plateau, wobble, col, layer):
        """Add one protrusion to ``layer`` (height, or the cluster's scratch by max) and blend
        its colour into the albedo; returns its peak height above the surface."""
        r0, r1 = int(cr) - margin, int(cr) + margin + 1
        c0, c1 = int(cc) - margin, int(cc) + margin + 1
        rr = np.arange(r0, r1)[:, None] - cr
        ccs = np.arange(c0, c1)[None, :] - cc
        u = ccs * np.cos(phi) + rr * np.sin(phi)
        v = -ccs * np.sin(phi) + rr * np.cos(phi)
        rho = np.sqrt((u / a) ** 2 + (v / b) ** 2)
        if wobble is not None:
            t = np.arctan2(v / b, u / a)
            rho = rho / (1 + sum(amp * np.cos(j * t + ph) for amp, j, ph
                                 in zip(wobble["amps"], (2, 3, 5), wobble["phases"])))
        fine = np.linspace(0, 1, 2001)
        peak = float(_profile(fine, gamma, crater, plateau).max())
        if layer is self.height:
            self.height[r0:r1, c0:c1] += h_dome * _profile(rho, gamma, crater, plateau)
        else:
            np.maximum(layer[r0:r1, c0:c1], h_dome * _profile(rho, gamma, crater, plateau),
                       out=layer[r0:r1, c0:c1])
        sub = self.albedo[r0:r1, c0:c1]
        wgt = np.clip((1 - rho) * a, 0, 1)[..., None]
        sub[:] = sub * (1 - wgt) + col * wgt
        return h_dome * peak

    def occupy(self, cr, cc, a_reach, margin):
        """Mark a placed protrusion's disc (its reach + 1 px) as taken, so none overlaps it."""
        r0, r1 = int(cr) - margin, int(cr) + margin + 1
        c0, c1 = int(cc) - margin, int(cc) + margin + 1
        rr = np.arange(r0, r1)[:, None] - cr
        ccs = np.arange(c0, c1)[None, :] - cc
        self.occupied[r0:r1, c0:c1] |= rr ** 2 + ccs ** 2 <= (a_reach + 1.0) ** 2
        if self.on_f > 0:
            self.prot_occ[r0:r1, c0:c1] |= rr ** 2 + ccs ** 2 <= (a_reach + 1.0) ** 2

    def record(self, cr, cc, w_um, peak, geometry, weak, dark, region, aspect, phi, cluster):
        """Append one protrusion's row to the truth table."""
        for key, val in zip(_TABLE_KEYS, (cr, cc, w_um, peak, geometry == "crater", weak, region,
                                          aspect, math.degrees(phi), geometry, cluster, dark)):
            self.table[key].append(val)
        if self.on_f > 0:
            self.table["on_stroke"].append(bool(self.on_now))

    def place_in_region(self, reg, light):
        """Draw the number of protrusions of colour area ``reg`` from its density (light or dark
        paint) and place them widest first, so the big ones still find room."""
        spec, rng, px = self.spec, self.rng, self.px
        idx = np.flatnonzero(self.flat == reg)
        area_cm2 = idx.size * px * px / _UM2_PER_CM2
        density = spec.protrusion_density_light if light else spec.protrusion_density_dark
        count = int(rng.poisson(density * area_cm2))
        if count == 0:
            return
        idx_near = idx[self.near_stroke[idx]] if self.on_f > 0 else idx[:0]
        for w_um in np.sort(_protrusion_widths(rng, count, spec.width_um, spec.width_median_um))[::-1]:
            self.place_one(reg, w_um, idx, idx_near)

    def footprint(self, w_um):
        """Draw a protrusion's kind and geometry (from the shapes' stream) and its aspect; return
        them with its semi-axes, reach and stamp margin in pixels (the area that of a circle of
        diameter ``w_um``; a lumpy outline scaled to keep it)."""
        kind, geometry, wobble, plateau = None, None, None, None
        shapes = self.shapes
        if shapes is not None:
            kind = shapes.kind()
            geometry = kind if kind in PROTRUSION_GEOMETRIES else shapes.geometry()
            wobble = shapes.wobble() if geometry == "irregular" else None
            plateau = shapes.rng.uniform(0.4, 0.7) if geometry == "mesa" else None
        aspect = self.rng.uniform(1.0, 1.35)
        a = w_um / 2 * math.sqrt(aspect) / self.px                # semi-axes in pixels, area of
        b = w_um / 2 / math.sqrt(aspect) / self.px                # a circle of diameter w
        a_reach = a
        if wobble is not None:
            a, b = a * wobble["scale"], b * wobble["scale"]
            a_reach = a * wobble["reach"]
        margin = int(math.ceil(a_reach)) + 2
        return kind, geometry, wobble, plateau, aspect, a, b, a_reach, margin

    def find_spot(self, idx, idx_near, a_reach, margin):
        """Up to 40 tries at a centre in the area (near a stroke when ``on_now``) whose disc is
        inside the frame and free; None when all 40 fail. On or against a stroke only
        protrusions and the rest block it, not the stroke itself."""
        rng, (m, n) = self.rng, self.shape
        for _ in range(40):
            if self.on_now:
                j = idx_near[self.srng.integers(idx_near.size)]
            else:
                j = idx[rng.integers(idx.size)]
            cr = j // n + rng.uniform(-0.5, 0.5)
            cc = j % n + rng.uniform(-0.5, 0.5)
            if not (margin <= cr < m - margin and margin <= cc < n - margin):
                continue
            r0, r1 = int(cr) - margin, int(cr) + margin + 1
            c0, c1 = int(cc) - margin, int(cc) + margin + 1
            rr = np.arange(r0, r1)[:, None] - cr
            ccs = np.arange(c0, c1)[None, :] - cc
            busy = self.occupied[r0:r1, c0:c1]
            if self.on_now:
                busy = (busy & ~self.ridge_mask[r0:r1, c0:c1]) | self.prot_occ[r0:r1, c0:c1]
            if np.any(busy & (rr ** 2 + ccs ** 2 <= (a_reach + 1.5) ** 2)):
                continue
            return cr, cc
        return None

    def look(self, cr, cc, w_um, kind, geometry):
        """Draw a placed protrusion's orientation, height, profile, crater, and colour (bright
        soap, weakly fluorescing or dark: a tint of the paint under it)."""
        rng, spec = self.rng, self.spec
        phi = rng.uniform(0, np.pi)
        h_dome = self.clip_height(rng.uniform(0.15, 0.35) * w_um)
        gamma = rng.uniform(1.0, 1.6)
        has_crater = rng.random() < spec.crater_fraction
        if self.shapes is not None:
            has_crater = geometry == "crater"
        else:
            geometry = "crater" if has_crater else "dome"
        crater = (rng.uniform(0.3, 0.6), rng.uniform(0.3, 0.5)) if has_crater else None
        weak = rng.random() < spec.weak_fraction
        dark = kind == "dark"
        paint = self.albedo[int(cr), int(cc)]
        if dark:
            weak = False
            col = paint * self.shapes.rng.uniform(0.5, 1.0)
        elif weak:
            col = paint * rng.uniform(1.05, 1.2)
        else:
            col = self.colour * rng.uniform(0.92, 1.05)
        return phi, h_dome, gamma, geometry, crater, weak, dark, col

    def place_one(self, reg, w_um, idx, idx_near):
        """Place one protrusion of width ``w_um`` in area ``reg`` (dropped when no free spot is
        found), or a cluster of touching ones when its kind is "cluster"."""
        kind, geometry, wobble, plateau, aspect, a, b, a_reach, margin = self.footprint(w_um)
        self.on_now = self.on_f > 0 and idx_near.size > 0 and self.srng.random() < self.on_f
        spot = self.find_spot(idx, idx_near, a_reach, margin)
        if spot is None:
            return
        cr, cc = spot
        phi, h_dome, gamma, geometry, crater, weak, dark, col = self.look(cr, cc, w_um, kind, geometry)
        if kind != "cluster":
            peak = self.stamp(cr, cc, a, b, margin, phi, h_dome, gamma, crater, plateau, wobble,
                              col, self.height)
            self.occupy(cr, cc, a_reach, margin)
            self.record(cr, cc, w_um, peak, geometry, weak, dark, reg, aspect, phi, 0)
            return
        # a cluster: this one and 1-3 more touching it, added to the height by their maximum
        self.n_clusters += 1
        peak = self.stamp(cr, cc, a, b, margin, phi, h_dome, gamma, crater, plateau, wobble, col,
                          self.scratch)
        members = [(cr, cc, w_um / 2 / self.px, a_reach, margin)]
        self.record(cr, cc, w_um, peak, geometry, weak, False, reg, aspect, phi, self.n_clusters)
        self.cluster_members(members)

    def cluster_members(self, members):
        """Add 1-3 members touching the cluster's first (all from the shapes' stream), then add
        the cluster to the height by the members' maximum (so they merge, not stack) and mark
        them occupied; a cluster left with one member is recorded as a lone protrusion."""
        shapes, spec, px, scratch = self.shapes, self.spec, self.px, self.scratch
        for _ in range(int(shapes.rng.integers(1, 4))):
            placed = _cluster_member(shapes, spec, members, self.occupied, px, self.shape)
            if placed is None:
                continue
            (cr2, cc2, w2, aspect2, phi2, a2, b2, a_reach2, margin2, geometry2, wobble2,
             plateau2, crater2, gamma2) = placed
            h2 = self.clip_height(shapes.rng.uniform(0.15, 0.35) * w2)
            weak2 = shapes.rng.random() < spec.weak_fraction
            paint2 = self.albedo[int(cr2), int(cc2)]
            col2 = (paint2 * shapes.rng.uniform(1.05, 1.2) if weak2
                    else self.colour * shapes.rng.uniform(0.92, 1.05))
            peak2 = self.stamp(cr2, cc2, a2, b2, margin2, phi2, h2, gamma2, crater2, plateau2,
                               wobble2, col2, scratch)
            members.append((cr2, cc2, w2 / 2 / px, a_reach2, margin2))
            self.record(cr2, cc2, w2, peak2, geometry2, weak2, False,
                        self.labels[int(round(cr2)), int(round(cc2))], aspect2, phi2, self.n_clusters)
        if len(members) == 1:                  # no room for another: a lone protrusion
            self.table["cluster"][-1] = 0
            self.n_clusters -= 1
        r0 = min(int(c[0]) - c[4] for c in members)
        r1 = max(int(c[0]) + c[4] + 1 for c in members)
        c0 = min(int(c[1]) - c[4] for c in members)
        c1 = max(int(c[1]) + c[4] + 1 for c in members)
        self.height[r0:r1, c0:c1] += scratch[r0:r1, c0:c1]
        scratch[r0:r1, c0:c1] = 0.0
        for cr_, cc_, _, a_reach_, margin_ in members:
            self.occupy(cr_, cc_, a_reach_, margin_)

    def columns(self) -> dict:
        """The truth table as numpy columns, rows sorted by (row, column), ids 1..n."""
        table = self.table
        rows, cols = table["y_px"], table["x_px"]
        order = np.lexsort((np.asarray(cols), np.asarray(rows))) if rows else np.zeros(0, int)
        cols_ = {
            "x_px": np.asarray(cols, dtype=np.float64), "y_px": np.asarray(rows, dtype=np.float64),
            "width_um": np.asarray(table["width_um"], dtype=np.float64),
            "height_um": np.asarray(table["height_um"], dtype=np.float64),
            "crater": np.asarray(table["crater"], dtype=bool),
            "weak": np.asarray(table["weak"], dtype=bool),
            "region": np.asarray(table["region"], dtype=np.int32),
            "aspect": np.asarray(table["aspect"], dtype=np.float64),
            "angle_deg": np.asarray(table["angle_deg"], dtype=np.float64),
            "shape": np.asarray(table["shape"], dtype="<U9"),
            "cluster": np.asarray(table["cluster"], dtype=np.int32),
            "dark": np.asarray(table["dark"], dtype=bool),
            **({"on_stroke": np.asarray(table["on_stroke"], dtype=bool)} if self.on_f > 0 else {}),
        }
        out = {"id": np.arange(1, len(rows) + 1, dtype=np.int32)}
        out.update({k: v[order] for k, v in cols_.items()})
        return out


def _cluster_member(shapes, spec, members, occupied, px, shape):
    """Draw and place one more member touching a random member of a cluster: its centre
    0.7-0.85 x the sum of the two equivalent radii away (so the footprints overlap), off every
    other protrusion, ridge and primer spot. Returns its parameters, or None after 20 tries."""
    m, n = shape
    srng = shapes.rng
    w_um = min(max(members[0][2] * 2 * px * srng.uniform(0.5, 1.0), spec.width_um[0]),
               spec.width_um[1])
    geometry = shapes.geometry()
    wobble = shapes.wobble() if geometry == "irregular" else None
    plateau = srng.uniform(0.4, 0.7) if geometry == "mesa" else None
    crater = (srng.uniform(0.3, 0.6), srng.uniform(0.3, 0.5)) if geometry == "crater" else None
    gamma = srng.uniform(1.0, 1.6)
    aspect = srng.uniform(1.0, 1.35)
    phi = srng.uniform(0, np.pi)
    a = w_um / 2 * math.sqrt(aspect) / px
    b = w_um / 2 / math.sqrt(aspect) / px
    a_reach = a
    if wobble is not None:
        a, b = a * wobble["scale"], b * wobble["scale"]
        a_reach = a * wobble["reach"]
    margin = int(math.ceil(a_reach)) + 2
    radius = w_um / 2 / px
    for _ in range(20):
        cr0, cc0, r_eq, _, _ = members[srng.integers(len(members))]
        psi = srng.uniform(0, 2 * np.pi)
        d = (r_eq + radius) * srng.uniform(0.7, 0.85)
        cr, cc = cr0 + d * math.sin(psi), cc0 + d * math.cos(psi)
        if not (margin <= cr < m - margin and margin <= cc < n - margin):
            continue
        if any(math.hypot(cr - c[0], cc - c[1]) < 0.7 * (c[2] + radius) for c in members):
            continue
        r0, r1 = int(cr) - margin, int(cr) + margin + 1
        c0, c1 = int(cc) - margin, int(cc) + margin + 1
        rr = np.arange(r0, r1)[:, None] - cr
        ccs = np.arange(c0, c1)[None, :] - cc
        if np.any(occupied[r0:r1, c0:c1] & (rr ** 2 + ccs ** 2 <= (a_reach + 1.5) ** 2)):
            continue
        return (cr, cc, w_um, aspect, phi, a, b, a_reach, margin, geometry, wobble, plateau,
                crater, gamma)
    return None
