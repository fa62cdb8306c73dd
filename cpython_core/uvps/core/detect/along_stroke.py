"""The along-stroke rescue: bumps on strokes measured again over the stroke's own profile
continued along the stroke (module docstring of :mod:`uvps.core.detect`, step 8)."""
from __future__ import annotations

import math
from typing import NamedTuple

import cv2
import numpy as np
from scipy import ndimage as ndi

from ._common import Thresholds, _edt
from .candidates import Candidates
from .features import CandidateFeatures, _axis_lengths, _crack_fraction
from .params import DetectionParams
from .rules import RuleContext, _rescue_fails
from .surface import Surface


#: A bump's peak over the stroke's continuation is at most this many times the candidate's
#: relief over its surround: more, and the line cut through another structure (a crossing
#: stroke, a bend) rather than a bump off the stroke.
RESCUE_PEAK_BOUND = 2.0
#: The shortest line (px) of the opening: shorter, a 3-4 px bump's own top would stay in it.
MIN_LINE_PX = 9.0


class _Bump(NamedTuple):
    """A bump's own measurements, as the rules marked ``rescue`` read them (:func:`.rules._rescue_fails`):
    its footprint's equivalent diameter and elongation (px), its outline's axes (px), its peak
    excess (um), its outline's crack fraction (0 unless it was drawn with the cracks filled),
    hole fraction 0, the candidate's mismatch, its outline's unmeasured and total pixels."""

    eqd: float
    elongation: float
    major: float
    minor: float
    relief: float
    crack_fraction: float
    hole_fraction: float
    mismatch: float
    unmeasured_px: int
    area_px: int


def _stroke_direction(h: np.ndarray, inner: np.ndarray, r_px: float) -> float:
    """Direction (rad from the column axis toward increasing row) in which the height around a
    candidate runs on: perpendicular to the dominant gradient of the annulus 1 to ``2 r + 2`` px
    from it (the structure tensor; across a stroke its flanks' gradient dominates)."""
    dist = _edt(~inner)
    ann = (dist > 1) & (dist <= 2 * r_px + 2)
    gy, gx = np.gradient(h.astype(np.float64))
    gx, gy = gx[ann], gy[ann]
    across = 0.5 * math.atan2(2 * float(gx @ gy), float(gx @ gx - gy @ gy))
    return across + 0.5 * math.pi


def _line_opening(h: np.ndarray, theta: float, length_px: float) -> np.ndarray:
    """Grey opening of ``h`` by a line ``length_px`` long at angle ``theta``
    (:func:`cv2.morphologyEx` with a line drawn by :func:`cv2.line`): what runs on along the line
    for at least its length stays, a bump shorter than it along the line is cut to its foot."""
    k = max(3, int(length_px) | 1)
    c = k // 2
    dx, dy = c * math.cos(theta), c * math.sin(theta)
    se = np.zeros((k, k), np.uint8)
    cv2.line(se, (round(c - dx), round(c - dy)), (round(c + dx), round(c + dy)), 1, 1)
    return cv2.morphologyEx(h.astype(np.float32), cv2.MORPH_OPEN, se,
                            borderType=cv2.BORDER_REFLECT)


def _excess_bump(h: np.ndarray, inner: np.ndarray, r_px: float, floor_um: float,
                 p: DetectionParams, crack_px: float = 0.0) -> tuple:
    """A candidate's bump over the stroke's profile continued along the stroke.

    The excess ``e = h - line opening`` along the stroke's direction, the line
    ``along_stroke_k`` x the candidate's radius long: the stroke's cross-profile runs on beyond
    the candidate and stays in the opening, a bump on it does not. Its footprint: ``e`` above
    ``footprint_fraction`` of its peak in the candidate (and ``floor_um``), connected to that
    peak; its outline (the label drawn): the part of the footprint also above the stroke's own
    excess around it (the largest ``e`` beyond ``r + 2`` px: ripple crests cut by the same
    line; at most half the peak), so the ripple under a bump is not counted in its width.
    Returns (footprint, outline, peak excess um), or (None, None, 0) when the footprint reaches
    the crop's border (not closed: the height does not run on as a stroke does)."""
    base = h
    if crack_px > 0:
        # cracks filled first (a closing by the crack width, the groove the ``crack`` rule
        # measures): a crack crossing the line would drop the opening to its floor along the
        # whole line and open the excess of a protrusion that merely touches it
        k = 2 * int(math.ceil(crack_px / 2)) + 1
        se = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
        base = cv2.morphologyEx(h.astype(np.float32), cv2.MORPH_CLOSE, se,
                                borderType=cv2.BORDER_REFLECT)
    theta = _stroke_direction(base, inner, r_px)
    e = h - _line_opening(base, theta, max(p.along_stroke_k * r_px, MIN_LINE_PX))
    seed = np.unravel_index(int(np.argmax(np.where(inner, e, -np.inf))), e.shape)
    peak = float(e[seed])
    parts = []
    away = _edt(~inner) > r_px + 2
    own = float(e[away].max()) if away.any() else 0.0
    base = max(p.footprint_fraction * peak, floor_um)
    for level in (base, max(base, min(own, 0.5 * peak))):
        comp, _ = ndi.label(e >= level, structure=np.ones((3, 3)))
        if comp[seed] == 0:
            return None, None, 0.0
        parts.append(comp == comp[seed])
    foot = parts[0]
    if foot[0].any() or foot[-1].any() or foot[:, 0].any() or foot[:, -1].any():
        return None, None, 0.0
    return foot, parts[1], peak


def _outline_crack_fraction(h: np.ndarray, outline: np.ndarray, peak: float, floor_um: float,
                            crack_px: float) -> float:
    """The ``crack`` rule's quantity (:func:`_crack_fraction`) for one bump's outline in its
    crop: the fraction of the 2-px ring around it in a crack at least half as deep as the bump
    is high. A protrusion touching a crack keeps most of its ring on the paint; the corner of a
    cupped island, whose lips rise toward the cracks around it, is bounded by them."""
    ring = (_edt(~outline) <= 2) & ~outline
    return float(_crack_fraction(outline.astype(np.int32), ring.astype(np.int32), h,
                                 np.array([peak]), 1, crack_px, floor_um)[0])


def _bumps_on_strokes(cand: Candidates, surf: Surface, f: CandidateFeatures, reason, th: Thresholds,
                      px: float, p: DetectionParams, stroke_min: float, ripple: np.ndarray,
                      unmeasured: np.ndarray = None) -> tuple:
    """Keep the closed bumps on strokes that the ``ridge``, ``crack`` and ``stroke`` rules reject.

    Tested: candidates with a long structure under them (``under`` >= the relief threshold):
    compact peaks (height cue) that these rules reject, and glowing candidates without a compact
    peak that ``ridge`` rejects (a small protrusion on the flank of a taller stroke has no
    relief enclosed within ``L`` of its own: every level set through its top reaches the
    stroke's crest; only the albedo finds it). Each one's excess over the stroke's continuation
    (:func:`_excess_bump`) must be closed, ``min_width_um``-``max_width_um`` wide, at most
    ``ridge_elongation`` elongated, its outline no ridge by its second moments (axis ratio at
    least ``ridge_axis_ratio`` when ``ridge_min_length_um`` long: on a footprint a few pixels
    wide the inscribed radius is pixelised, the axes are not), its flank slope (peak / half
    width) at least the strokes' own least slope (:func:`_stroke_slope`) and the weave's, the
    candidate's mismatch with the normals at most ``max_mismatch`` (a bump the integration made
    on a crack's lip is no protrusion, whichever rule rejected it first), its
    peak at least the relief threshold and at most twice the candidate's relief over its
    surround (over a local plane for a compact peak, over the disc opening for a glowing one;
    more: the line cut through another structure, a crossing stroke or a bend), and it must
    overlap no kept candidate. An excess that runs open while the candidate touches a crack is
    measured again with the cracks filled (a closing by ``crack_width_um``: a groove across the
    line drops the opening to its floor), and is then kept only when its outline passes the
    ``crack`` rule's raw count (every groove pixel of its ring in its crop, without the running
    test of :func:`_grooves_run_on`: a protrusion touches a crack, the corner of a cupped island
    is bounded by them). "Touches a crack" is a crack fraction above 0; one whose grooves over
    ``max_crack_fraction`` were all pockets reads 0 and is not measured again. Like every
    candidate, at most ``max_unmeasured_fraction`` of the outline may lie near pixels without a
    measurement (``unmeasured``, :func:`_unmeasured`). A kept one is relabelled to its outline.
    Returns (reasons, labels)."""
    lab, reason = cand.labels.copy(), reason.copy()
    if p.along_stroke_k <= 0:
        return reason, lab
    glow = f.has_a & ~f.has_h
    bound = np.where(f.has_h, f.relief, f.relief_disc)
    test = np.flatnonzero(((np.isin(reason, ("ridge", "crack", "stroke")) & f.has_h)
                           | ((reason == "ridge") & glow)) & (f.under >= th.relief_um) & ~ripple
                          & (f.mismatch <= p.max_mismatch))
    kept = np.zeros(int(lab.max()) + 1, bool)
    kept[f.lbl[reason == ""]] = True
    slices, (m, n) = ndi.find_objects(lab), lab.shape
    ctx = RuleContext(th, px, p, on_long=True, stroke_min=stroke_min, ripple=False)
    for j in test:
        k, sl = int(f.lbl[j]), slices[int(f.lbl[j]) - 1]
        own = cand.height if f.has_h[j] else lab     # a glowing one: its whole candidate
        r = math.sqrt(max(np.count_nonzero(own[sl] == k), 1) / math.pi)
        pad = int(4 * r + 6)
        crop = (slice(max(sl[0].start - pad, 0), min(sl[0].stop + pad, m)),
                slice(max(sl[1].start - pad, 0), min(sl[1].stop + pad, n)))
        region = lab[crop]
        foot, outline, peak = _excess_bump(surf.height[crop], region == k, r, th.relief_um, p)
        cracked = foot is None and f.crack_fraction[j] > 0
        if cracked:         # open along a crack it touches: again with the cracks filled
            foot, outline, peak = _excess_bump(surf.height[crop], region == k, r, th.relief_um,
                                                p, p.crack_width_um / px)
        if foot is None or kept[region[foot]].any():
            continue
        area = float(np.count_nonzero(foot))
        eqd = 2 * math.sqrt(area / math.pi)
        elong = area / (math.pi * float(_edt(np.pad(foot, 1)).max()) ** 2)
        # the second moments as well: on a footprint a few pixels wide the inscribed radius
        # is pixelised (a 6 x 20 px piece of stroke reads 2x elongated), its axes are not
        major, minor = (float(a[0]) for a in _axis_lengths(outline.astype(np.int32), 1))
        crack = 0.0
        if cracked:
            crack = _outline_crack_fraction(surf.height[crop], outline, peak, th.relief_um,
                                            p.crack_width_um / px)
        unm = 0 if unmeasured is None else np.count_nonzero(unmeasured[crop][outline])
        bump = _Bump(eqd=eqd, elongation=elong, major=major, minor=minor, relief=peak,
                     crack_fraction=crack, hole_fraction=0.0, mismatch=f.mismatch[j],
                     unmeasured_px=unm, area_px=np.count_nonzero(outline))
        if not _rescue_fails(bump, ctx) and peak <= RESCUE_PEAK_BOUND * bound[j]:
            region[region == k] = 0
            region[outline] = k
            kept[k], reason[j] = True, ""
    return reason, lab
