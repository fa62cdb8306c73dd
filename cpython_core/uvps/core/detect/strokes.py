"""The strokes' own statistics (module docstring of :mod:`uvps.core.detect`, step 6): which
candidates are bumps on long structures, their least flank slope, and the ripple test."""
from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from ._common import Thresholds, _on_long_structure
from .features import CandidateFeatures
from .params import DetectionParams


#: The strokes' own least slope is measured only over at least this many bumps on long
#: structures: a median of fewer is one stroke's accident, not the image's statistics (with
#: fewer, the slope test tests nothing; the ripple test still runs).
STROKE_MIN_BUMPS = 8
#: The ripple test (:func:`_ripples`): two neighbours in a row are similar crests when their
#: equivalent diameters are within 1.6 x and their reliefs within 2 x of the bump's (a brush's
#: ripples vary by about that much along a stroke), on opposite sides when their directions from
#: it are at least 150 deg apart (a stroke curves a little over three crests), and evenly spaced
#: when their distances are within 1.5 x of each other.
RIPPLE_WIDTH_RATIO = 1.6
RIPPLE_RELIEF_RATIO = 2.0
RIPPLE_OPPOSITE_DEG = 150.0
RIPPLE_SPACING_RATIO = 1.5


def _stroke_slope(f: CandidateFeatures, th: Thresholds, px: float, p: DetectionParams) -> tuple:
    """The strokes' own statistics: which candidates are bumps on a long structure (a compact
    peak with a long structure under it at least the relief threshold and a quarter of its
    relief high, no albedo glow), and the least flank slope a protrusion among them must have:
    ``stroke_slope_k`` x their median flank slope (inf-free: 0 with fewer than 8 of them, then
    no candidate is tested). Returns (on_long mask, least slope)."""
    slope = f.relief / np.maximum(f.eqd * px / 2, 1e-12)
    on_long = f.has_h & ~f.has_a & _on_long_structure(f.under, f.relief, th)
    if p.stroke_slope_k <= 0 or on_long.sum() < STROKE_MIN_BUMPS:
        return on_long, 0.0
    return on_long, float(p.stroke_slope_k * np.median(slope[on_long]))


def _ripples(f: CandidateFeatures, on_long: np.ndarray, p: DetectionParams) -> np.ndarray:
    """Which bumps on long structures are a stroke's ripples: periodic crests, not an event.

    A bump ``j`` of the strokes' population (``on_long``, :func:`_stroke_slope`: no glow) is a
    ripple when two others of that population, each 1/1.6-1.6 x its equivalent diameter ``d``
    and 1/2-2 x its relief, lie within ``ripple_reach x d`` of it on opposite sides (their
    directions from it at least 150 deg apart) at distances within 1.5 x of each other: it is
    the middle of an evenly spaced row of similar crests, as a brush's ripples are (every 1-2
    crest widths along the stroke). The ends of a row are ripples too when the row holds four
    or more (the other end of their triple is the middle of the next triple along the row); a
    row of three keeps its ends, even where another row crosses it at an end. A bump centred on
    ``j``'s centre has no direction from it and is left out of ``j``'s rows. Every candidate of
    the population counts as a neighbour, whatever rule rejects it, so a row stays a row where
    some of its crests fail another test. A protrusion is an event: a row of similar,
    non-glowing ones at even spacing is the case this test gets wrong (the glowing ones are
    never tested). The relief keeps a protrusion that erupts through a rippled stroke out of its
    row: on the end-to-end captures (docs/decisions/detection.md, "End to end, change by
    change") two weakly glowing ones 200-230 um wide stood 55-70 um over their surround, between
    crests a fifth as high. Hand-written: no library tests collinear, evenly spaced neighbours;
    the neighbours come from :class:`scipy.spatial.cKDTree`. Returns a mask."""
    out = np.zeros(f.lbl.size, bool)
    pop = np.flatnonzero(on_long)
    if p.ripple_reach <= 0 or pop.size < 3:
        return out
    tree = cKDTree(f.centroid[pop])
    d = f.eqd
    triples = []                                     # (middle, one end, the other end)
    cos_max = math.cos(math.radians(RIPPLE_OPPOSITE_DEG))
    for j, near in zip(pop, tree.query_ball_point(f.centroid[pop], p.ripple_reach * d[pop])):
        q = pop[np.asarray(near, dtype=np.intp)]
        q = q[(q != j) & (d[q] >= d[j] / RIPPLE_WIDTH_RATIO) & (d[q] <= RIPPLE_WIDTH_RATIO * d[j])
              & (f.relief[q] >= f.relief[j] / RIPPLE_RELIEF_RATIO)
              & (f.relief[q] <= RIPPLE_RELIEF_RATIO * f.relief[j])]
        v = f.centroid[q] - f.centroid[j]
        r = np.hypot(v[:, 0], v[:, 1])
        q, v, r = q[r > 0], v[r > 0], r[r > 0]       # a centroid on j's own: no direction
        if q.size < 2:
            continue
        cos = (v @ v.T) / np.outer(r, r)
        ratio = r[:, None] / r[None, :]
        a, b = np.nonzero(np.triu((cos < cos_max) & (ratio <= RIPPLE_SPACING_RATIO)
                                  & (ratio >= 1 / RIPPLE_SPACING_RATIO)))
        triples += [(j, int(x), int(y)) for x, y in zip(q[a], q[b])]
    beside = {(m, e) for m, x, y in triples for e in (x, y)}     # e is beside m in a row through m
    for m, x, y in triples:
        out[m] = True
        # a row of four or more, x m y z: m is also beside y in the row (m, y, z); a row of three,
        # or another row crossing through y, keeps x
        out[x] |= (y, m) in beside
        out[y] |= (x, m) in beside
    return out
