"""Features: the per-candidate quantities the rejection rules read (:class:`CandidateFeatures`)."""
from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage as ndi

from ..threads import concurrently
from ._common import (STEPS_4, Thresholds, _edt, _expand_labels, _holes, _label_max, _label_mean,
                      _touching)
from .candidates import HEIGHT, Candidates
from .params import DetectionParams
from .surface import Surface


#: A candidate glows (``has_a``) when at least this share of its pixels (and one) lies in the
#: albedo mask: a height footprint grown into its own glow holds much more; one whose foot
#: merely touches a bright neighbour's halo holds a few pixels.
GLOW_SHARE = 0.2


#: The ring (px) around a candidate whose height is its surround (the ``crack`` rule's ring; the
#: relief's ring is at least this and a quarter of the smallest width + 1 px): 2 px clears the
#: foot's last pixel and its smoothing, and stays on the paint next to it.
RING_PX = 2.0


@dataclass
class CandidateFeatures:
    """Per-candidate quantities tested by :data:`REJECTION_RULES` (lengths in px, heights in um)."""

    lbl: np.ndarray             # label ids, increasing
    area: np.ndarray
    eqd: np.ndarray             # equivalent diameter
    relief: np.ndarray          # compact relief: peak over the surrounding ring
    relief_disc: np.ndarray     # relief over the disc opening (long structures included)
    elongation: np.ndarray      # area / (pi r_in^2)
    axis_ratio: np.ndarray      # minor / major axis (1 when not computed)
    major: np.ndarray
    hole_fraction: np.ndarray
    has_h: np.ndarray           # a compact peak (height cue)
    has_a: np.ndarray           # >= 20 % of its pixels from the albedo cue
    own_glow: np.ndarray        # its albedo pixels / the area of the albedo components it overlaps
    crack_fraction: np.ndarray  # of its 2-px ring in a crack at least half as deep as it is high
    under: np.ndarray           # mean relief of a long structure under it (disc top-hat - t), um
    tilt_deg: np.ndarray        # mean tilt of the normals (inf without normals)
    mismatch: np.ndarray        # height's slope off the normals' / the normals' (0 without)
    unmeasured: np.ndarray      # of its footprint within 2 px of a pixel with no measurement
    centroid: np.ndarray        # (K, 2) row, column of each candidate's centre of area


def _axis_lengths(lab: np.ndarray, n: int) -> tuple:
    """Per label 1..n, the major and minor axis lengths (px) of the ellipse with the same
    second central moments: ``skimage.measure.regionprops``' ``axis_major_length`` and
    ``axis_minor_length`` (4 sqrt of the inertia tensor's eigenvalues), from per-label sums
    (``np.bincount``) in one pass instead of one moments call per region (1.6 s for 1000
    regions at 4000 x 3000). Tested against regionprops in ``tests/test_detect.py``."""
    rr, cc = np.nonzero(lab)
    lb = lab[rr, cc]
    cnt = np.maximum(np.bincount(lb, minlength=n + 1)[1:n + 1], 1)

    def centred(v):
        mean = np.bincount(lb, weights=v, minlength=n + 1)[1:n + 1] / cnt
        return v - np.concatenate([[0.0], mean])[lb]

    dr, dc = centred(rr.astype(np.float64)), centred(cc.astype(np.float64))
    mu = [np.bincount(lb, weights=w, minlength=n + 1)[1:n + 1] / cnt
          for w in (dr * dr, dc * dc, dr * dc)]
    half_sum, half_diff = 0.5 * (mu[0] + mu[1]), 0.5 * (mu[0] - mu[1])
    root = np.hypot(half_diff, mu[2])
    return (4 * np.sqrt(np.maximum(half_sum + root, 0)),
            4 * np.sqrt(np.maximum(half_sum - root, 0)))


def _inscribed_radius(lab: np.ndarray, n: int) -> np.ndarray:
    """Largest inscribed radius per label (px): the largest distance from one of its pixels to
    the nearest pixel outside it (touching labels count as outside), its unlabelled holes filled:
    a crater's collapsed centre, a few pixels below the footprint's level, would halve the radius
    and read as elongation (``ridge``); the hole itself is judged by ``max_hole_fraction``.

    Each label in its own crop, its box widened by 1 px: a label touching no other has, along
    its row and its column, an unlabelled pixel within that ring, nearer than any pixel beyond
    it, so the crop's distances are the whole image's (a whole-image transform cost 0.5 s at
    4000 x 3000 for candidates covering a tenth of it)."""
    r_in = np.full(n, -np.inf)
    touching = np.zeros(n + 1, bool)
    first, second = _touching(lab, STEPS_4)
    touching[lab.ravel()[first]] = touching[lab.ravel()[second]] = True
    for i, s in enumerate(ndi.find_objects(lab), start=1):
        if s is None:
            continue
        sl = tuple(slice(max(k.start - 1, 0), k.stop + 1) for k in s)
        crop = lab[sl]
        own = ndi.binary_fill_holes(crop == i) & ((crop == i) | (crop == 0))
        if touching[i]:
            r_in[i - 1] = _edt(np.pad(own, 1)).max()
        else:
            r_in[i - 1] = _edt((crop > 0) | own)[own].max()
    return np.maximum(r_in, 0.5)


def _crack_fraction(lab: np.ndarray, ring: np.ndarray, hn: np.ndarray, relief: np.ndarray,
                    n: int, crack_px: float, floor_um: float, check_above: float = None,
                    known: np.ndarray = None) -> np.ndarray:
    """Per label, the fraction of the 2-px ring around it lying in a crack: a groove narrower
    than ``crack_px`` (black top-hat: closing by that disc, minus the height) at least half as
    deep as the label is high (and ``floor_um``), below the ring's mean height (a notch between
    touching protrusions lies above it). A protrusion may touch a crack; a piece of a cupped
    island's rim, or of a stroke crossing it, is cut off by one along a whole side. ``ring``:
    the labels expanded by 2 px outside them.

    With ``check_above``, a label whose fraction exceeds it is measured again counting only the
    grooves that run on (:func:`_grooves_run_on`): a crack is a line that runs on beyond the
    label, the pocket between touching protrusions is closed by them. ``known``: pixels known
    to be a crack's (a run's ``left_out`` band: its walls' gradients were left out of the
    height, so the height there is the integration's fill and the groove may not run on in
    it); a groove within 2 px of them is a crack's."""
    k = 2 * int(math.ceil(crack_px / 2)) + 1
    se = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (k, k))
    depth = cv2.morphologyEx(hn, cv2.MORPH_CLOSE, se, borderType=cv2.BORDER_REFLECT) - hn
    need = np.concatenate([[np.inf], np.maximum(0.5 * relief, floor_um)])
    at = np.flatnonzero(ring)                            # the ring's pixels only
    rl, h_at = ring.ravel()[at], hn.ravel()[at]
    level = np.concatenate([[-np.inf], _label_mean(h_at, rl, n)])
    below = h_at < level[rl]
    total = np.bincount(rl, minlength=n + 1)[1:n + 1]
    hit = np.bincount(rl[(depth.ravel()[at] >= need[rl]) & below], minlength=n + 1)[1:n + 1]
    frac = np.where(total > 0, hit / np.maximum(total, 1), 0.0)
    if check_above is not None:
        redo = np.flatnonzero(frac > check_above)
        slices = ndi.find_objects(ring, max_label=n) if redo.size else []
        for i in redo:
            if slices[i] is not None:
                frac[i] = _grooves_run_on(lab, ring, hn, depth, slices[i], i + 1, need[i + 1],
                                          level[i + 1], 2.0 * crack_px, floor_um,
                                          known) / max(total[i], 1)
    return frac


def _grooves_run_on(lab: np.ndarray, ring: np.ndarray, hn: np.ndarray, depth: np.ndarray,
                    sl: tuple, k: int, need: float, level: float, reach_px: float,
                    floor_um: float, known: np.ndarray = None) -> int:
    """How many of label ``k``'s ring pixels (``ring``'s slice ``sl`` holds them) lie in a groove
    (``depth`` >= ``need``, ``hn`` below ``level``: :func:`_crack_fraction`'s test) that runs on
    at least ``reach_px`` beyond the label: the groove's component (8-connected, in the label's
    crop padded by that much), followed where it is at least half as deep (and ``floor_um``: a
    crack's depth under the black top-hat varies along it), reaches a pixel that far from it,
    the image's border, or within 2 px of a pixel of ``known`` (a crack's,
    :func:`_crack_fraction`). A crack is a line through the paint; the pocket between touching
    protrusions, which the black top-hat reads as deep too, ends where they do. On the true
    maps the ring pixels that rejected three 88-95 um protrusions lay in such pockets, none on a
    crack, while the pieces of paint the rule rejects lay on cracks all round (docs/protrusions.md,
    "A crack runs on, a pocket between protrusions does not"). The groove is followed only below
    the ring's mean height (``level``): on steeply tilted paint a crack climbing away from the
    label can be cut short of ``reach_px`` and read as a pocket; and where the height was not
    measured it holds the median fill, which ends a groove too. Hand-written: a component's reach from an object is no library's measurement."""
    m, nc = lab.shape
    pad = int(math.ceil(reach_px)) + 1
    crop = (slice(max(sl[0].start - pad, 0), min(sl[0].stop + pad, m)),
            slice(max(sl[1].start - pad, 0), min(sl[1].stop + pad, nc)))
    below = (hn[crop] < level) & (lab[crop] != k)
    own = (ring[crop] == k) & (depth[crop] >= need) & below
    groove = (depth[crop] >= max(0.5 * need, floor_um)) & below
    comp, n_comp = ndi.label(groove, structure=np.ones((3, 3)))
    if not n_comp:
        return 0
    far = _edt(lab[crop] != k) >= reach_px
    # the image's border cuts a groove short: one reaching it runs on beyond
    far[0] |= crop[0].start == 0
    far[-1] |= crop[0].stop == m
    far[:, 0] |= crop[1].start == 0
    far[:, -1] |= crop[1].stop == nc
    if known is not None and known[crop].any():
        far |= cv2.dilate(known[crop].astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    runs = np.zeros(n_comp + 1, bool)
    runs[comp[groove & far]] = True
    runs[0] = False
    return int(np.count_nonzero(runs[comp[own]]))


def _hole_area(lab: np.ndarray, n: int) -> np.ndarray:
    """Area (px) of the holes each label encloses on its own (holes bordered by one label).

    A hole's rim: the labelled pixels whose 3 x 3 neighbourhood holds it (the highest hole
    there, as a grey dilation of the hole labels gives), found in each hole's crop: holes
    are few, a full-image dilation and ``ndimage.minimum`` cost 2 s at 4000 x 3000."""
    holes, k = _holes(lab > 0)
    if not k:
        return np.zeros(n)
    m, nc = lab.shape
    lo = np.full(k + 1, np.iinfo(np.int32).max, np.int64)
    hi = np.zeros(k + 1, np.int64)
    for i, sl in enumerate(ndi.find_objects(holes)):
        # the dilation is exact 1 px inside a crop padded by 2 (rim pixels lie within 1 px)
        r0, c0 = max(sl[0].start - 2, 0), max(sl[1].start - 2, 0)
        big = (slice(r0, min(sl[0].stop + 2, m)), slice(c0, min(sl[1].stop + 2, nc)))
        rim = ndi.grey_dilation(holes[big], size=(3, 3)) == i + 1
        rim &= lab[big] > 0
        if rim.any():
            vals = lab[big][rim]
            lo[i + 1], hi[i + 1] = vals.min(), vals.max()
    size = np.bincount(holes.ravel(), minlength=k + 1)
    own = (lo == hi) & (hi > 0)
    return np.bincount(hi[own], weights=size[own].astype(np.float64), minlength=n + 1)[1:n + 1]


def _odd_at(h: np.ndarray, rr: np.ndarray, cc: np.ndarray, axis: int) -> np.ndarray:
    """``h`` (float64) at pixels one of whose coordinates, along ``axis``, may lie 1 px beyond the
    image: there its odd reflection ``2 h[edge] - h[edge -+ 1]`` (one-sided differences at the edges),
    the values of ``np.pad(h.astype(np.float64), 1, mode="reflect", reflect_type="odd")`` read at
    those pixels, without its two full-size float64 copies (0.18 GB at 4000 x 3000, at the
    detection's peak of memory: scripts/benchmark_speed.py)."""
    size = h.shape[axis]
    idx = rr if axis == 0 else cc
    inside = np.clip(idx, 0, size - 1)
    at = (lambda i: h[i, cc]) if axis == 0 else (lambda i: h[rr, i])
    v = at(inside).astype(np.float64)
    out = (idx < 0) | (idx >= size)
    if out.any():
        edge = np.where(idx < 0, 0, size - 1)[out]
        mirror = np.where(idx < 0, 1, size - 2)[out]
        sub = (lambda i: h[i, cc[out]]) if axis == 0 else (lambda i: h[rr[out], i])
        v[out] = 2 * sub(edge).astype(np.float64) - sub(mirror).astype(np.float64)
    return v


def _normals_features(normals, h, lab, n, px: float, left_out=None) -> tuple:
    """Per label 1..n: the mean tilt of the normals (deg) and how far the height's slope departs
    from the normals' (``p = -nx/nz``, ``q = -ny/nz`` in the frame of ``docs/architecture.md``),
    a common tilt over the label set aside: mean |e - mean e| / mean |g - mean g|, ``e`` the
    difference of the two slopes and ``g`` the normals' slope. Without normals: inf and 0.

    ``left_out``: pixels whose gradients the height was integrated without (a crack's walls,
    :func:`uvps.core.pipeline.detection_height`): the height departs from the normals there by
    construction, so a label's mismatch is measured over its other pixels when they are at
    least half of it (a label mostly on such pixels keeps the mismatch over all of them)."""
    if normals is None:
        return np.full(n, np.inf), np.zeros(n)
    rr, cc = np.nonzero(lab)                         # only the candidates' pixels
    lb = lab[rr, cc]
    nrm = np.asarray(normals)[rr, cc].astype(np.float64)
    nz = np.clip(np.where(np.isfinite(nrm[:, 2]), nrm[:, 2], 1), -1, 1)
    tilt = _label_mean(np.degrees(np.arccos(nz)), lb, n)
    nz = np.maximum(nz, 0.05)
    g = (np.nan_to_num(-nrm[:, 0] / nz), np.nan_to_num(-nrm[:, 1] / nz))
    d_col = (_odd_at(h, rr, cc + 1, 1) - _odd_at(h, rr, cc - 1, 1)) / (2 * px)
    d_row = (_odd_at(h, rr + 1, cc, 0) - _odd_at(h, rr - 1, cc, 0)) / (2 * px)
    e = (d_col - g[0], -d_row - g[1])                # y is up: dz/dy = -dz/d(row)
    if left_out is not None:                         # the mismatch over the pixels off the band,
        off = left_out[rr, cc]                       # where they are at least half the label
        area = np.bincount(lb, minlength=n + 1)
        rest = np.bincount(lb[~off], minlength=n + 1)
        keep = ~off | (rest < 0.5 * area)[lb]
        lb, g, e = lb[keep], (g[0][keep], g[1][keep]), (e[0][keep], e[1][keep])

    def spread(vx, vy):
        mx = np.concatenate([[0.0], _label_mean(vx, lb, n)])[lb]
        my = np.concatenate([[0.0], _label_mean(vy, lb, n)])[lb]
        return _label_mean(np.hypot(vx - mx, vy - my), lb, n)

    return tilt, spread(*e) / np.maximum(spread(*g), 1e-6)


def _candidate_features(cand: Candidates, surf: Surface, normals, th: Thresholds, px: float,
                        p: DetectionParams, unmeasured: np.ndarray = None,
                        left_out: np.ndarray = None) -> CandidateFeatures:
    """Measure every candidate (a height candidate's relief is the one over its local plane);
    ``unmeasured``: :func:`_unmeasured` (None: every pixel measured); ``left_out``:
    :func:`_normals_features`."""
    lab, t_disc = cand.labels, cand.t_disc
    n_lab = int(lab.max())
    area_all = np.bincount(lab.ravel(), minlength=n_lab + 1)[1:]
    lbl = np.flatnonzero(area_all) + 1
    area = area_all[lbl - 1].astype(np.float64)
    eqd = np.sqrt(4 * area / np.pi)
    t = surf.relief
    is_h = cand.kind[lbl] == HEIGHT
    # the shapes and the normals' measures read the labels alone: beside the reliefs over the rings
    (relief, crack, relief_disc), (radius, holes, glow_area, (tilt, mismatch)) = concurrently(
        lambda: _ring_reliefs(cand, surf, lbl, is_h, th, px, p, left_out),
        lambda: (_inscribed_radius(lab, n_lab), _hole_area(lab, n_lab), _glow_area(lab, n_lab, cand.glow),
                 _normals_features(normals, surf.raw, lab, n_lab, px, left_out)))
    elong = area / (np.pi * radius[lbl - 1] ** 2)
    holes, glow_area = holes[lbl - 1], glow_area[lbl - 1]
    n_alb = np.bincount(lab[cand.mask_albedo], minlength=n_lab + 1)[lbl]
    own_glow = np.where(glow_area > 0, n_alb / np.maximum(glow_area, 1), 0.0)
    major = np.zeros(lbl.size)
    ratio = np.ones(lbl.size)
    need = (eqd >= th.min_w) & (eqd <= th.max_w) & (elong <= p.ridge_elongation)
    if need.any():  # the axes only where they can decide something
        ax_major, ax_minor = _axis_lengths(lab, n_lab)
        major[need] = ax_major[lbl[need] - 1]
        ratio[need] = ax_minor[lbl[need] - 1] / np.maximum(major[need], 1e-9)
    under = _label_mean(t_disc - t, lab, n_lab)[lbl - 1]
    rr, cc = np.nonzero(lab)
    ll = lab[rr, cc]
    centroid = np.column_stack([np.bincount(ll, rr, minlength=n_lab + 1)[lbl],
                                np.bincount(ll, cc, minlength=n_lab + 1)[lbl]]) / area[:, None]
    unm = np.zeros(lbl.size)
    if unmeasured is not None:
        unm = np.bincount(ll, unmeasured[rr, cc], minlength=n_lab + 1)[lbl] / area
    return CandidateFeatures(under=under, lbl=lbl, centroid=centroid, area=area, eqd=eqd, relief=relief,
                             relief_disc=relief_disc, elongation=elong, axis_ratio=ratio, major=major,
                             hole_fraction=holes / (area + holes),
                             has_h=is_h, has_a=n_alb >= np.maximum(1, GLOW_SHARE * area),
                             own_glow=own_glow,
                             crack_fraction=crack, tilt_deg=tilt[lbl - 1],
                             mismatch=mismatch[lbl - 1], unmeasured=unm)


def _ring_reliefs(cand: Candidates, surf: Surface, lbl, is_h, th: Thresholds, px: float,
                  p: DetectionParams, left_out) -> tuple:
    """:func:`_candidate_features`' measures over the rings around the candidates ``lbl``: relief
    (a height candidate's: over its local plane), crack fraction, relief of the disc top-hat."""
    lab, t_disc, t = cand.labels, cand.t_disc, surf.relief
    n_lab = int(lab.max())
    ring_w = max(RING_PX, 0.25 * th.min_w + 1)
    ring = _expand_labels(lab, ring_w)
    ring *= lab == 0            # in place (int32 times bool: the same labels), no second label image
    if ring_w == RING_PX:
        ring2 = ring
    else:
        ring2 = _expand_labels(lab, RING_PX)
        ring2 *= lab == 0
    relief = (_label_max(t, lab, n_lab) - _label_mean(t, ring, n_lab))[lbl - 1]
    relief[is_h] = cand.height_relief[lbl[is_h] - 1]
    rel_all = np.zeros(n_lab)
    rel_all[lbl - 1] = relief
    crack = _crack_fraction(lab, ring2, surf.height, rel_all, n_lab, p.crack_width_um / px,
                            th.relief_um, check_above=p.max_crack_fraction, known=left_out)[lbl - 1]
    relief_disc = (_label_max(t_disc, lab, n_lab) - _label_mean(t_disc, ring, n_lab))[lbl - 1]
    return relief, crack, relief_disc


def _glow_area(lab: np.ndarray, n_lab: int, glow: np.ndarray) -> np.ndarray:
    """Per label 1..n_lab, the area of the albedo components (``glow``) it overlaps (0 where it
    overlaps none). A candidate's albedo pixels over it are its own glow
    (``CandidateFeatures.own_glow``): a protrusion's glow is its own spot, a piece of a glowing
    stroke holds a small part of the glowing paint it is cut from."""
    size = np.bincount(glow.ravel())
    both = (glow > 0) & (lab > 0)
    pairs = np.unique(glow[both].astype(np.int64) * (n_lab + 1) + lab[both])
    comp, owner = pairs // (n_lab + 1), pairs % (n_lab + 1)
    return np.bincount(owner, weights=size[comp], minlength=n_lab + 1)[1:]


def _unmeasured(measured: np.ndarray, normals) -> np.ndarray:
    """The pixels within 2 px of one without a measurement: outside ``measured`` (a finite height
    and albedo), or a non-finite normal (the photometric stereo's holes: a crack's floor, a
    shadow; ``mask`` is a choice, not one of them). None where every pixel has one."""
    unknown = ~measured
    if normals is not None:
        unknown |= ~np.isfinite(np.asarray(normals)).all(axis=2)
    if not unknown.any():
        return None
    disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (5, 5))
    return cv2.dilate(unknown.view(np.uint8), disc, borderType=cv2.BORDER_CONSTANT,
                      borderValue=0).view(bool)
