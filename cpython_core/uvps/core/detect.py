"""Automated metal-soap protrusion detection from the height map and the fluorescence albedo.

The paper (Salvant et al., "Automated Protrusion Detection") builds mask 1 from a colour threshold
plus template matching on the albedo and mask 2 from OpenCV blob detection on the height map, and
takes their union; it under-counts and is fooled by brush-stroke ridges and bare primer. Here every
threshold is a physical quantity measured on the data (the height noise, the weave's spectrum) or
a stated property of a protrusion, and each cue is one function (``docs/architecture.md``,
"Detection cues", says what each assumes):

1. **Surface** (:func:`_surface`). The height noise is a robust MAD of the high-passed height
   (second differences). The canvas weave, a few sharp peaks of the height's power spectrum, is
   measured (periods, RMS amplitude, RMS slope) and subtracted (:func:`_remove_weave`).
2. **Compact relief** (:func:`_compact_relief`). ``t = h - min(h, A(h))``, ``A`` the *diameter
   opening*: every level set of ``h`` whose extent reaches ``L = 1.3 x max_width_um`` stays in
   ``A``, so ``t`` holds only what is enclosed within less than ``L``: protrusions (domes, craters,
   mesas, any outline) stand out; the canvas bow, brush strokes, cupped islands and crack lips
   (all longer than ``L``) vanish. ``A`` is computed on f x f block maxima (``f = L / 16`` px, 5 at
   15 um per pixel); a small object in the block next to a stroke's is then taken into the
   stroke's level sets, so around such objects the exact level sets decide (:func:`_beside_long`).
3. **Height cue** (:func:`_height_cue`, :func:`_local_footprints`). Peaks of ``t`` at least the
   relief threshold ``max(min_dynamic_um, dynamic_k x smoothed noise)`` high, two peaks being two
   protrusions when the saddle between them lies ``split_fraction`` below the lower one, or
   ``weak_split_fraction`` below it when the lower one is at most three quarters as high and
   the two do not lie along a ridge (:func:`_weak_splits`); a smaller dome on a taller one's
   flank with no peak of its own is marked by the blob its curvature makes there
   (:func:`_shoulder_markers`). A watershed of ``-t`` from the markers splits touching
   clusters. Each footprint is then re-drawn over a robust plane through its
   surround (a protrusion on a slope keeps its whole relief), where the relief exceeds
   ``footprint_fraction`` of its peak.
4. **Albedo cue** (:func:`_albedo_cue`). Brightness contrast ``L / L_bg - 1`` above
   ``albedo_contrast`` whose component matches a disc template (:func:`cv2.matchTemplate`). It
   only adds: a protrusion that does not fluoresce is found by its relief alone.
5. **Long raised areas** (:func:`_long_areas`). What a disc top-hat raises but ``t`` does not
   (strokes, crack lips) become candidates, so that the ``ridge`` rule counts them.
6. **The strokes' own statistics** (:func:`_stroke_slope`). Compact peaks with a long structure
   under them (a stroke's ripples, piled ends and crossings, or a protrusion on a stroke) and
   no albedo glow; their median flank slope, measured per image, sets the least slope of a
   protrusion among them (``stroke_slope_k`` times it; the ``stroke`` rule). Among them, the
   members of an evenly spaced row of similar bumps are a stroke's ripples (:func:`_ripples`),
   rejected by the same rule whatever their slope.
7. **Union** (:func:`_union`) and **rejection** (:func:`_candidate_features`,
   :func:`_apply_rules`) by the table :data:`REJECTION_RULES`, first match wins; each rejected
   candidate keeps its rule (``Detection.diagnostics["candidate_reasons"]``), the counts are
   ``Detection.rejected``.
8. **Bumps on strokes** (:func:`_bumps_on_strokes`). A compact peak on a long structure that the
   ``ridge``, ``crack`` or ``stroke`` rule rejects, or a glowing candidate without a compact
   peak on one (a small protrusion on a taller stroke's flank), is measured again over the
   stroke's own profile continued along the stroke (the height, cracks filled where they cut
   it, minus its opening by a line laid in the direction the height around it runs on): a
   closed, compact bump as steep as the strokes' own statistics ask, whose height the normals
   hold (the ``artefact`` rule's mismatch), is a protrusion on the stroke and is kept, outlined
   by that excess.

Every length option is in micrometres and converted with ``pixel_size_um``.
"""
from __future__ import annotations

import heapq
import logging
import math
from dataclasses import dataclass, field, replace
from typing import Callable, NamedTuple, Optional

import cv2
import numba
import numpy as np
import scipy.fft
from scipy import ndimage as ndi
from scipy.spatial import cKDTree
from skimage.morphology import h_maxima, max_tree
from skimage.segmentation import expand_labels, watershed

from ..errors import UVPSInputError, check_pixel_size

logger = logging.getLogger(__name__)

__all__ = ["DetectionParams", "Detection", "detect_protrusions", "REJECTION_REASONS",
           "REJECTION_RULES", "RejectionRule"]

Progress = Optional[Callable[[float, str], None]]


class RejectionRule(NamedTuple):
    """One row of the rejection table: the rule's name, the quantity it tests, the test."""

    name: str
    quantity: str
    test: str


#: The rejection table, applied in this order (a candidate keeps the first rule it fails).
REJECTION_RULES = (
    RejectionRule("too_small", "equivalent diameter 2 sqrt(area / pi)", "< min_width_um"),
    RejectionRule("ridge", "elongation area / (pi r_in^2) (r_in: largest inscribed radius); "
                  "minor / major axis; compact fraction (relief within L / relief over the "
                  "surround, for raised areas without a compact peak)",
                  "elongation > ridge_elongation, or axis ratio < ridge_axis_ratio with a major "
                  "axis >= ridge_min_length_um, or compact fraction < ridge_compact_fraction"),
    RejectionRule("stroke", "on a long structure (the disc top-hat exceeds the compact relief under "
                  "it by the relief threshold and a quarter of its relief), without the albedo's "
                  "glow: flank slope relief / (width / 2)",
                  "< stroke_slope_k x the median flank slope of the bumps on long structures "
                  "(measured per image, at least 8 of them): a ripple, a piled end or a crossing "
                  "of a brush stroke; or a member of an evenly spaced row of similar such bumps "
                  "(_ripples: a stroke's ripples) (ridge, stroke and crack: unless its excess "
                  "over the stroke's profile continued along the stroke is a closed, steep bump "
                  "whose mismatch is within max_mismatch, _bumps_on_strokes; never for a ripple)"),
    RejectionRule("crack", "crack fraction: of the 2-px ring around it, the part in a crack (black "
                  "top-hat over crack_width_um) at least half as deep as it is high, counted where "
                  "the groove runs on 2 crack widths beyond it (a pocket between touching "
                  "protrusions ends with them); hole fraction: "
                  "area enclosed by the footprint but below its level / filled area",
                  "crack fraction > max_crack_fraction (a piece of a cupped island's rim or of a "
                  "stroke cut off by a crack), or hole fraction > max_hole_fraction (a crater's "
                  "floor stands above the paint, a cupped island's rim encloses its dish)"),
    RejectionRule("too_large", "equivalent diameter", "> max_width_um"),
    RejectionRule("flat_bright", "relief (um) of a candidate found by the albedo only; mean tilt",
                  "relief < relief threshold or tilt < 1 deg: bare primer"),
    RejectionRule("artefact", "mismatch: over the footprint, mean |e - mean e| / mean |g - mean g|, "
                  "g the normals' slope, e the height's slope minus g (with normals only); "
                  "unmeasured fraction: the part of the footprint within 2 px of a pixel with no "
                  "measurement (non-finite albedo, normals or height)",
                  "mismatch > max_mismatch: relief the normals do not hold is an integration "
                  "artefact (e.g. along a crack whose walls the lamps do not light; the pixels "
                  "left out of the height's integration, left_out, set aside when the rest is at "
                  "least half the footprint); or unmeasured "
                  "fraction > max_unmeasured_fraction: relief made by the integration's fill of a hole"),
    RejectionRule("weave", "relief (um); flank slope relief / (width / 2); mean tilt; own glow: "
                  "of the albedo components it overlaps, the part inside it",
                  "relief < relief threshold, or slope < max(2 min_relief_ratio, weave_slope_k x "
                  "the weave's RMS slope) unless it glows and its own glow is at least "
                  "own_glow_fraction (the weave does not glow; a piece of a glowing stroke holds "
                  "a small part of the glowing paint it is cut from): then max(relief, relief over "
                  "the disc opening) / (width / 2) < 2 min_relief_ratio; or tilt < 1 deg"),
)
REJECTION_REASONS = tuple(r.name for r in REJECTION_RULES)


@dataclass
class DetectionParams:
    """Options of :func:`detect_protrusions`. Lengths and heights in um.

    Attributes
    ----------
    min_width_um, max_width_um : float
        Accepted equivalent-circle diameters of a protrusion; ``max_width_um`` also sets the
        compact-relief length ``L = 1.3 x max_width_um``.
    smooth_um : float
        Gaussian sigma applied to the height (and to the brightness for the albedo cue) before
        detection, in um; below 0.3 px (at more than 25 um per pixel at 7.5) nothing is
        smoothed. 7.5 (half a pixel at 15 um per pixel) keeps more of the saddles, a micrometre
        or two deep, between touching protrusions 60-100 um wide than 10 did
        (``docs/benchmarks.md``); the height's noise sets the relief threshold through it.
    min_dynamic_um : float
        Floor of the relief threshold (um): a protrusion rises at least this much.
    dynamic_k : float
        Relief threshold in multiples of the smoothed height noise (measured).
    split_fraction : float
        Two touching peaks are separate protrusions when the saddle between them lies at least
        this fraction of the lower peak's relief below it.
    weak_split_fraction : float
        A peak whose saddle lies between this and ``split_fraction`` of its relief below it is a
        protrusion of its own when it is at most :data:`WEAK_HOST_RATIO` (3/4) as high as the
        tallest peak it touches (a cluster member on a taller neighbour's flank; the lumps of a
        crater's rim are of a height) and the two are not elongated together as a ridge (a
        rippled pile of paint) (:func:`_weak_splits`). In [0, 1); 0 (or ``split_fraction`` and
        above) disables.
    crest_fraction : float
        Over a footprint's local plane, touching peaks whose saddle lies less than this fraction
        of the lower one's relief below it are one crest (a lip or a stroke cut into bumps).
    footprint_fraction : float
        Footprint: pixels whose relief (over the local plane, else the compact relief) exceeds
        this fraction of the peak's.
    weave_factor : float
        Spectral peaks (periods between ``weave_min_period_um`` and ``weave_max_period_um``)
        more than this many times the median power at their frequency are the weave, fitted as
        sinusoids and subtracted from the height. 0 disables.
    weave_min_period_um, weave_max_period_um : float
        Period band searched for the weave.
    weave_slope_k : float
        A protrusion's flank slope (relief / half width) exceeds this many times the weave's RMS
        slope (a sine's steepest slope is sqrt(2) x its RMS slope).
    min_relief_ratio : float
        Floor of relief / width (half the flank slope): paint texture is flatter than this,
        protrusions are 0.1-0.4.
    own_glow_fraction : float
        A glowing candidate (at least 20 % of it from the albedo cue) that holds at least this
        fraction of the albedo components it overlaps (its glow is its own spot, shared at most
        with a touching neighbour; an albedo-only candidate is its whole component, so for it
        the exemption holds whenever it glows) meets ``2 x min_relief_ratio`` instead of the
        weave's slope, with the larger of its local relief and its relief over the disc opening
        (over the mean of its ring): the weave does not glow, a glowing protrusion on a piled
        stroke end's foot rises 4-5 um over the local plane through its ring, a third of its
        height, and one on a stroke's curved flank keeps only its top as its relief. A piece
        of a glowing stroke holds 3-18 % of the glowing paint it is cut from, a protrusion
        38-100 % of its glow (``docs/benchmarks.md``, "Detection on other shapes and surfaces").
        Above 1 disables.
    albedo_contrast : float
        Relative brightness above the local background for the albedo mask (0.15 = 15 %).
    template_ncc : float
        Minimum normalised correlation with a disc template for an albedo component.
    template_scales : int
        Number of disc diameters, geometric between ``min_width_um`` and ``max_width_um``.
    ridge_elongation : float
        Area / (pi r_in^2) above which a candidate is a ridge (a disc is 1, an ellipse of
        aspect a is a; a stroke's piece of length l and width w about 4 l / (pi w)).
    ridge_axis_ratio, ridge_min_length_um : float
        Minor/major axis ratio below which a candidate at least ``ridge_min_length_um`` long is
        a ridge.
    ridge_compact_fraction : float
        A raised area without a compact peak whose relief within ``L`` is below this fraction of
        its relief over the surround is part of a long structure (stroke, crack lip).
    stroke_slope_k : float
        A bump on a long structure (a stroke's ripple, piled end or crossing) that does not glow
        is kept only when its flank slope exceeds this many times the median flank slope of the
        bumps on long structures in the image (the strokes' own statistics). 0 disables this
        slope test (the ripple test, ``ripple_reach``, is apart).
    along_stroke_k : float
        A compact peak on a long structure that the ``ridge``, ``crack`` or ``stroke`` rule
        rejects (or a glowing candidate without a compact peak that ``ridge`` rejects) is
        measured again over the stroke's own profile continued along the stroke: the
        height minus its grey opening by a line this many times the peak's compact radius long,
        in the direction the height around it runs on (:func:`_bumps_on_strokes`); kept only
        when its mismatch with the normals is within ``max_mismatch``. 0 disables.
    shoulder_width_um : float
        Width (um) of the small protrusions sought as shoulders of a taller neighbour (no saddle
        ``split_fraction`` below them): the height cue also splits a footprint at the dome-like
        maxima of the compact relief's curvature (minus its Laplacian of Gaussian, sigma =
        this width / (2 sqrt 2)) that stand ``shoulder_k`` x the curvature's noise above the
        saddle to a higher curvature peak (:func:`_shoulder_markers`). The default, 60,
        finds 60-100 um shoulders (``docs/benchmarks.md``, "Detection on other shapes and
        surfaces"); 0 disables. A shoulder is at most :data:`WEAK_HOST_RATIO` of its basin's
        peak high and on no long structure (:func:`_shoulder_markers`).
    shoulder_k : float
        Least dynamic of such a curvature peak in multiples of the measured curvature noise
        (MAD over the image), and at least the curvature of a dome ``shoulder_width_um`` wide
        and the relief threshold high.
    shoulder_isotropy : float
        Least ratio of the Hessian's two (negative) eigenvalues at a shoulder peak: a dome is
        curved down all round (ratio near 1); a mesa's or a crater's rim, a stroke's crest, only
        across (ratio near 0).
    max_hole_fraction : float
        Largest fraction of a candidate's filled outline that may lie below its footprint
        level (cupped island rims enclose their dish).
    max_crack_fraction : float
        Largest fraction of the 2-px ring around a candidate that may lie in a crack at least
        half as deep as the candidate is high (a protrusion may touch a crack, not run along it).
        A groove counts as a crack where it runs on at least two ``crack_width_um`` beyond the
        candidate (:func:`_grooves_run_on`): the pocket of paint between touching protrusions,
        as deep under the black top-hat, ends with them.
    max_mismatch : float
        With normals: largest mean departure of the height's slope from the normals' over a
        candidate (a common tilt set aside), relative to the spread of the normals' slope over
        it (0 for a height integrated exactly); measured away from ``left_out`` pixels when they
        are less than half the candidate (:func:`detect_protrusions`). The along-stroke cue
        keeps no candidate above it.
    max_unmeasured_fraction : float
        Largest fraction of a candidate's footprint that may lie within 2 px of a pixel without
        a measurement (non-finite albedo, normals or height; not ``mask``): where the lamps gave
        no normal (the floor of a crack, a shadow), the integration fills the hole, and the fill
        rises and falls at its edge. On the end-to-end captures of docs/benchmarks.md the 16
        false positives made so lay 91-100 % within 2 px of such pixels, and no protrusion
        found has more than a fifth of its footprint there.
    albedo_grow_um : float
        How far (um) the albedo outline may extend a height footprint: by the pixels of its
        own glow (an albedo component that overlaps the footprint), not of bright paint beside it.
    crack_width_um : float
        Cracks are grooves narrower than this (the ``crack`` rule's black top-hat).
    curl_k : float
        Curl threshold (robust standard deviations) of the non-integrable gradients left out of the
        height a run's detection reads; 0 reads the run's height as it is. Used by
        :func:`uvps.core.pipeline.find_protrusions` where the normals are given: the height is integrated
        again (Frankot-Chellappa) without the gradients of patches longer than ``max_width_um``
        whose curl exceeds it (:func:`uvps.core.integrate.nonintegrable_patches`: crack walls, whose
        relief would otherwise spread along the strokes and raise the ``stroke`` rule's bar).
        15 sits above the 99th percentile of the curl outside the cracks of the benchmark's captures
        (12) and far below its median inside them (84); end-to-end figures in docs/benchmarks.md.
    beside_long_fraction : float
        A small object that the compact relief's block maxima join to a stroke, a crack lip or a
        taller neighbour beside it (in the next block: 5 px at 15 um per pixel) gets its exact
        compact relief when it rises above the saddle where it joins them by at least this
        fraction of its height over the paint's lowest envelope (the disc top-hat), and by twice
        the relief threshold (:func:`_beside_long`). In [0, 1); 0 disables.
    ripple_reach : float
        A bump on a long structure without glow is a stroke's ripple (``stroke`` rule) when it is
        in an evenly spaced row of similar ones (the middle of three, or any of four or more), its
        neighbours in the row within this many of its equivalent diameters (:func:`_ripples`).
        0 disables.
    """

    min_width_um: float = 30.0
    max_width_um: float = 1000.0
    smooth_um: float = 7.5
    min_dynamic_um: float = 1.0
    dynamic_k: float = 5.0
    split_fraction: float = 0.15
    crest_fraction: float = 0.05
    footprint_fraction: float = 0.1
    weave_factor: float = 50.0
    weave_min_period_um: float = 150.0
    weave_max_period_um: float = 3000.0
    weave_slope_k: float = 2.0
    min_relief_ratio: float = 0.05
    own_glow_fraction: float = 1.0 / 3.0
    albedo_contrast: float = 0.15
    template_ncc: float = 0.5
    template_scales: int = 4
    ridge_elongation: float = 3.0
    ridge_axis_ratio: float = 0.4
    ridge_min_length_um: float = 150.0
    ridge_compact_fraction: float = 0.5
    stroke_slope_k: float = 3.0
    along_stroke_k: float = 6.0
    shoulder_width_um: float = 60.0
    shoulder_k: float = 5.0
    shoulder_isotropy: float = 0.6
    max_hole_fraction: float = 0.25
    max_crack_fraction: float = 0.08
    max_mismatch: float = 0.5
    max_unmeasured_fraction: float = 0.5
    albedo_grow_um: float = 60.0
    crack_width_um: float = 90.0
    curl_k: float = 15.0
    ripple_reach: float = 2.5
    beside_long_fraction: float = 0.15
    weak_split_fraction: float = 0.10


@dataclass
class Detection:
    """Result of :func:`detect_protrusions`.

    Attributes
    ----------
    labels : (M, N) int32
        0 = background, 1..n one id per protrusion.
    source : (n,) str
        Per label (``source[i]`` for label ``i + 1``): "albedo", "height" or "albedo+height".
    mask_albedo, mask_height : (M, N) bool
        The two cue masks (before rejection).
    rejected : dict
        Counts of rejected candidates by rule (:data:`REJECTION_REASONS`).
    noise_um : float
        Height noise estimate (um) used for the thresholds.
    diagnostics : dict
        Thresholds (``relief_um``, ``slope_min``, ``length_um``), the measurements they come from
        (``noise_smoothed_um``, ``weave_periods_um``, ``weave_rms_um``, ``weave_slope_rms``,
        ``weave_peaks``), counts (``candidates``, ``height_candidates``,
        ``albedo_only_candidates``, ``long_candidates``), ``rejection_rules`` (the table) and
        ``candidate_labels`` ((M, N) int32, every candidate before rejection) with
        ``candidate_reasons`` (per candidate, "" = kept), for overlays.
    """

    labels: np.ndarray
    source: np.ndarray
    mask_albedo: np.ndarray
    mask_height: np.ndarray
    rejected: dict
    noise_um: float = float("nan")
    diagnostics: dict = field(default_factory=dict)


@dataclass
class WeaveEstimate:
    """The canvas weave as measured from the height's spectrum (see :func:`_remove_weave`)."""

    periods_um: list
    rms_um: float = 0.0
    slope_rms: float = 0.0
    n_peaks: int = 0


@dataclass
class Surface:
    """The height prepared for the cues (see :func:`_surface`)."""

    raw: np.ndarray             # the height with invalid pixels filled (um)
    height: np.ndarray          # smoothed, weave removed, invalid pixels filled (um)
    relief: np.ndarray          # compact relief t >= 0 (um)
    disc: np.ndarray            # height over its opening by a disc L wide (um)
    noise_um: float
    noise_smoothed_um: float
    weave: WeaveEstimate
    length_px: float


class Thresholds(NamedTuple):
    relief_um: float            # least relief of a protrusion (and of a peak over a saddle)
    slope_min: float            # least flank slope relief / (width / 2)
    min_w: float                # px
    max_w: float                # px


def _report(progress: Progress, fraction: float, message: str) -> None:
    if progress is not None:
        progress(float(fraction), message)


def _validate(albedo, height_um, pixel_size_um, normals, mask, params, left_out=None):
    h = np.asarray(height_um)
    if h.ndim != 2:
        raise UVPSInputError(f"`height_um` must be (M, N); got shape {h.shape}")
    a = np.asarray(albedo)
    if not (a.shape == h.shape or (a.ndim == 3 and a.shape[:2] == h.shape and a.shape[2] in (1, 3))):
        raise UVPSInputError(f"`albedo` must be (M, N) or (M, N, 3) with (M, N) = {h.shape}; got shape {a.shape}")
    px = check_pixel_size(pixel_size_um)
    if normals is not None and np.shape(normals) != h.shape + (3,):
        raise UVPSInputError(f"`normals` must be (M, N, 3) with (M, N) = {h.shape}; got shape {np.shape(normals)}")
    if mask is not None and np.shape(mask) != h.shape:
        raise UVPSInputError(f"`mask` must be (M, N) = {h.shape}; got shape {np.shape(mask)}")
    if left_out is not None and np.shape(left_out) != h.shape:
        raise UVPSInputError(f"`left_out` must be (M, N) = {h.shape}; got shape {np.shape(left_out)}")
    p = params if params is not None else DetectionParams()
    if not isinstance(p, DetectionParams):
        raise UVPSInputError(f"`params` must be a DetectionParams; got {type(p).__name__}")
    if not (0 < p.min_width_um < p.max_width_um):
        raise UVPSInputError(f"need 0 < min_width_um < max_width_um; got {p.min_width_um}, {p.max_width_um}")
    if not 0 <= p.beside_long_fraction < 1:
        raise UVPSInputError(f"beside_long_fraction must be in [0, 1); got {p.beside_long_fraction}")
    if not 0 <= p.weak_split_fraction < 1:
        raise UVPSInputError(f"weak_split_fraction must be in [0, 1); got {p.weak_split_fraction}")
    if not p.own_glow_fraction > 0:
        raise UVPSInputError(f"own_glow_fraction must be > 0 (above 1 disables); got {p.own_glow_fraction}")
    if not 0 <= p.max_unmeasured_fraction <= 1:
        raise UVPSInputError(f"max_unmeasured_fraction must be in [0, 1]; got {p.max_unmeasured_fraction}")
    if not (0 < p.split_fraction < 1 and 0 < p.footprint_fraction < 1):
        raise UVPSInputError(f"split_fraction and footprint_fraction must be in (0, 1); got "
                             f"{p.split_fraction}, {p.footprint_fraction}")
    if min(h.shape) < 8:
        raise UVPSInputError(f"`height_um` must be at least 8 x 8 pixels; got {h.shape}")
    return a, h, px, p


# --------------------------------------------------------------------------------------------
# Surface: noise, weave, compact relief
# --------------------------------------------------------------------------------------------


def _noise_sigma(h: np.ndarray, valid: np.ndarray) -> float:
    """Robust white-noise sigma of the height: MAD of its high-pass (second differences).

    A second difference cancels planes and slopes; for white noise its variance is 6 sigma^2.
    """
    across, along = h[:, 2:] - 2 * h[:, 1:-1] + h[:, :-2], h[2:] - 2 * h[1:-1] + h[:-2]
    if valid.all():
        d = np.concatenate([across.ravel(), along.ravel()])
    else:
        d = np.concatenate([across[valid[:, 2:] & valid[:, 1:-1] & valid[:, :-2]],
                            along[valid[2:] & valid[1:-1] & valid[:-2]]])
    if d.size == 0:
        return 0.0
    # d is ours: both medians partition it in place (the same multiset, the same medians)
    mad = np.median(np.abs(d - np.median(d, overwrite_input=True), out=d), overwrite_input=True)
    return float(1.4826 * mad / math.sqrt(6.0))


def _ring_median(power: np.ndarray, ring: np.ndarray, band: np.ndarray) -> np.ndarray:
    """Median of ``power`` over ``band`` per integer radial ring (0 where a ring is empty)."""
    sel, pb = ring[band], power[band]
    order = np.lexsort((pb, sel))
    rs, ps = sel[order], pb[order]
    starts = np.flatnonzero(np.r_[True, rs[1:] != rs[:-1]])
    counts = np.diff(np.r_[starts, rs.size])
    med = np.zeros(int(ring.max()) + 1)
    med[rs[starts]] = ps[starts + counts // 2]
    return med


def _peak_frequency(logp: np.ndarray, ky: int, kx: int) -> tuple:
    """Sub-bin frequency (cycles/px along rows, cols) of a spectral peak at bin (ky, kx) of an
    rfft2 spectrum: a parabola through the log power of the bin and its two neighbours per axis
    (Gaussian interpolation; exact for a Gaussian-windowed sinusoid, ~0.05 bin for Hann)."""
    m, nr = logp.shape
    n = 2 * (nr - 1)

    def vertex(a, b, c):
        den = a - 2 * b + c
        return 0.0 if den >= 0 else float(np.clip(0.5 * (a - c) / den, -0.5, 0.5))

    dy = vertex(logp[(ky - 1) % m, kx], logp[ky, kx], logp[(ky + 1) % m, kx])
    dx = vertex(logp[ky, kx - 1], logp[ky, kx], logp[ky, kx + 1]) if 0 < kx < nr - 1 else 0.0
    fy = (ky + dy) / m
    return (fy - 1.0 if fy >= 0.5 else fy), (kx + dx) / n


def _remove_weave(hs: np.ndarray, px: float, p: DetectionParams) -> tuple:
    """Measure the canvas weave on the height's power spectrum and subtract it.

    A weave is a few sharp peaks of the 2-D spectrum at periods of a few hundred um; a
    protrusion's spectrum is broad and smooth. On the Hann-windowed spectrum, bins whose power
    exceeds ``weave_factor`` times the median power at the same spatial frequency (periods in
    the searched band) are the weave's peaks; each peak's frequency is refined between bins
    (:func:`_peak_frequency`) and its sinusoid fitted by least squares over the image and
    subtracted. (Zeroing the bins instead leaves a third of the amplitude in the side lobes of a
    frequency between bins.) The fitted sinusoids give the weave's periods, RMS amplitude and
    RMS slope; the ``weave`` rule compares a candidate's flank slope with that slope.
    Returns (height without the weave, :class:`WeaveEstimate`).
    """
    none = WeaveEstimate(periods_um=[])
    if p.weave_factor <= 0:
        return hs, none
    m, n = hs.shape
    centred = hs.astype(np.float64) - float(np.mean(hs))
    win = np.outer(np.hanning(m), np.hanning(n))
    power = np.abs(scipy.fft.rfft2(centred * win)) ** 2
    fr = np.hypot(np.fft.fftfreq(m)[:, None], np.fft.rfftfreq(n)[None, :])  # cycles per pixel
    band = (fr >= px / p.weave_max_period_um) & (fr <= px / p.weave_min_period_um)
    if not band.any():
        return hs, none
    ring = np.minimum((fr * max(m, n)).astype(np.int64), max(m, n))
    med = _ring_median(power, ring, band)[ring]
    ratio = np.divide(power, med, out=np.zeros_like(power), where=band & (med > 0))
    lab, k = ndi.label(band & (ratio > p.weave_factor), structure=np.ones((3, 3)))
    if not k:
        return hs, none
    logp = np.log(power + 1e-300)
    # the peak bin of each component (labels are few; ndimage.maximum_position sorts them all)
    sel = np.flatnonzero(lab)
    order = np.lexsort((power.ravel()[sel], lab.ravel()[sel]))
    last = np.r_[np.flatnonzero(np.diff(lab.ravel()[sel][order])), order.size - 1]
    freqs = np.array([_peak_frequency(logp, *np.unravel_index(sel[order[i]], lab.shape))
                      for i in last])
    coef, gram = _fit_sinusoids(centred, freqs)
    comp = _sinusoids(freqs, coef, (m, n))
    periods = [round(px / math.hypot(fy, fx), 1) for fy, fx in freqs]
    mn = float(m * n)
    # mean square of the weave and of its slope (the analytic derivative), from the Gram matrix
    w2 = float(coef @ gram @ coef) / mn
    slope2 = 0.0
    for axis in (0, 1):
        scale = np.repeat(2 * np.pi * freqs[:, axis] / px, 2)
        dcoef = np.column_stack([coef[1::2], -coef[0::2]]).ravel() * scale  # d/dx cos = -sin
        slope2 += float(dcoef @ gram @ dcoef) / mn
    est = WeaveEstimate(periods_um=sorted(periods), rms_um=math.sqrt(max(w2, 0.0)),
                        slope_rms=math.sqrt(max(slope2, 0.0)), n_peaks=int(k))
    return (hs - comp).astype(np.float32), est


def _sinusoid_sums(freqs: np.ndarray, shape) -> callable:
    """``S(gy, gx) = sum over the image of exp(2 pi i (gy row + gx col))``, separable."""
    rows = np.arange(shape[0], dtype=np.float64)
    cols = np.arange(shape[1], dtype=np.float64)

    def total(gy, gx):
        return complex(np.exp(2j * np.pi * gy * rows).sum() * np.exp(2j * np.pi * gx * cols).sum())
    return total


def _fit_sinusoids(data: np.ndarray, freqs: np.ndarray) -> tuple:
    """Least-squares cosine and sine coefficients of the sinusoids ``freqs`` ((K, 2) cycles per
    pixel along rows, cols), fitted one after the other, each to what the previous left.

    Hand-written because the sinusoids are separable: each inner product with the image is one
    matrix product with 1-D exponentials, and those between two sinusoids are products of 1-D
    geometric sums, so no full-image cosine is ever formed (at 4000 x 3000 one costs 2 s per
    sinusoid). Returns (coefficients (2K,) as cos, sin per sinusoid; Gram matrix (2K, 2K))."""
    k = len(freqs)
    rows = np.arange(data.shape[0], dtype=np.float64)
    cols = np.arange(data.shape[1], dtype=np.float64)
    u = np.exp(2j * np.pi * np.outer(freqs[:, 0], rows))            # (K, M)
    v = np.exp(2j * np.pi * np.outer(freqs[:, 1], cols))            # (K, N)
    proj = np.einsum("kn,kn->k", u.real @ data + 1j * (u.imag @ data), v)
    total = _sinusoid_sums(freqs, data.shape)
    gram = np.zeros((2 * k, 2 * k))
    for a in range(k):
        for b in range(k):
            sp = total(*(freqs[a] + freqs[b]))
            sm = total(*(freqs[a] - freqs[b]))
            gram[2 * a, 2 * b] = 0.5 * (sp.real + sm.real)          # cos a . cos b
            gram[2 * a + 1, 2 * b + 1] = 0.5 * (sm.real - sp.real)  # sin a . sin b
            gram[2 * a, 2 * b + 1] = 0.5 * (sp.imag - sm.imag)      # cos a . sin b
            gram[2 * a + 1, 2 * b] = 0.5 * (sp.imag + sm.imag)      # sin a . cos b
    rhs_all = np.column_stack([proj.real, proj.imag]).ravel()       # cos, sin . data
    coef = np.zeros(2 * k)
    for a in range(k):
        i = slice(2 * a, 2 * a + 2)
        rhs = rhs_all[i] - gram[i, :2 * a] @ coef[:2 * a]
        coef[i] = np.linalg.lstsq(gram[i, i], rhs, rcond=None)[0]
    return coef, gram


def _sinusoids(freqs: np.ndarray, coef: np.ndarray, shape) -> np.ndarray:
    """``sum_k c_k cos(ph_k) + s_k sin(ph_k)`` as two real matrix products (float32)."""
    rows = np.arange(shape[0], dtype=np.float64)
    cols = np.arange(shape[1], dtype=np.float64)
    u = np.exp(2j * np.pi * np.outer(rows, freqs[:, 0])) * (coef[0::2] - 1j * coef[1::2])
    v = np.exp(2j * np.pi * np.outer(freqs[:, 1], cols))
    return (u.real @ v.real - u.imag @ v.imag).astype(np.float32)


def _block_max(img: np.ndarray, f: int) -> np.ndarray:
    """Maximum over f x f blocks (edge-padded to whole blocks)."""
    m, n = img.shape
    mb, nb = -(-m // f), -(-n // f)
    pad = np.pad(img, ((0, mb * f - m), (0, nb * f - n)), mode="edge")
    return pad.reshape(mb, f, nb, f).max(axis=(1, 3))


@numba.njit(nogil=True, cache=True)
def _diameter_filter(flat, parent, order, ncols, threshold):  # pragma: no cover - compiled
    """The diameter opening on a max-tree (``parent``, ``order`` of
    :func:`skimage.morphology.max_tree`): each node's bounding box gathered from its children
    in one pass up the tree, then each pixel keeps its level when its node's extension
    (largest side of the box) reaches ``threshold``, else its parent's output."""
    n = flat.size
    rmin = np.empty(n, np.int32)
    rmax = np.empty(n, np.int32)
    cmin = np.empty(n, np.int32)
    cmax = np.empty(n, np.int32)
    for i in range(n):
        r = i // ncols
        rmin[i] = r
        rmax[i] = r
        cmin[i] = i - r * ncols
        cmax[i] = i - r * ncols
    for k in range(n - 1, 0, -1):              # children before their parents
        i = order[k]
        q = parent[i]
        rmin[q] = min(rmin[q], rmin[i])
        rmax[q] = max(rmax[q], rmax[i])
        cmin[q] = min(cmin[q], cmin[i])
        cmax[q] = max(cmax[q], cmax[i])
    out = np.empty_like(flat)
    out[order[0]] = flat[order[0]]
    for k in range(1, n):                      # parents before their children
        i = order[k]
        q = parent[i]
        if flat[i] == flat[q]:                 # a pixel of its parent's level component
            out[i] = out[q]
        elif max(rmax[i] - rmin[i], cmax[i] - cmin[i]) + 1 >= threshold:
            out[i] = flat[i]
        else:
            out[i] = out[q]
    return out


def _diameter_opening(image: np.ndarray, threshold: int) -> np.ndarray:
    """:func:`skimage.morphology.diameter_opening` (4-connected), the same values.

    Hand-written after the max-tree (which skimage builds): skimage's extension pass took 80 %
    of the opening's time (30 of 37 s on a 636 x 836 block image under load; this one 1 s), so
    the bounding boxes are gathered here in one compiled pass up the tree. Tested against
    skimage's in ``tests/test_detect.py``."""
    img = np.ascontiguousarray(image)
    parent, order = max_tree(img, connectivity=1)
    return _diameter_filter(img.ravel(), parent.ravel(), order, img.shape[1],
                            int(threshold)).reshape(img.shape)


def _block_factor(length_px: float) -> int:
    """The side ``f`` of the blocks :func:`_compact_relief` opens: ``length_px / f`` is 16-32 px
    (``f`` = 1 below 32 px)."""
    return max(1, int(length_px // 16))


def _compact_relief(hn: np.ndarray, valid: np.ndarray, length_px: float) -> np.ndarray:
    """Relief enclosed within ``length_px``: ``hn - min(hn, A)``, A the diameter opening.

    The diameter opening keeps every connected level set whose bounding box reaches
    ``length_px`` (Breen and Jones 1996, via :func:`skimage.morphology.diameter_opening`), so what
    remains above it is compact: protrusions, not strokes, lips or bow. It runs on f x f block
    maxima (f so that ``length_px / f`` is ~16 px; cost ~0.5 s for 1600 x 1200 pixels), mirrored
    by ``length_px`` at the borders (a stroke leaving the image stays long), and repeated back to
    full size: a block maximum is never below the pixels it covers, so long structures stay in
    ``A`` to the pixel and only compact ones lose it. (Closing cracks first, so that a crack does
    not cut a lip or a stroke into compact pieces, also joins crowded protrusions into long
    chains; the ``crack`` rule deals with such pieces instead.)
    """
    f = _block_factor(length_px)
    m, n = hn.shape
    pad = int(math.ceil(length_px / f))
    coarse = cv2.copyMakeBorder(_block_max(hn, f), pad, pad, pad, pad, cv2.BORDER_REFLECT)
    opened = _diameter_opening(coarse, pad)[pad:-pad, pad:-pad]
    up = np.repeat(np.repeat(opened, f, axis=0), f, axis=1)[:m, :n]
    t = (hn - np.minimum(hn, up)).astype(np.float32)
    t[~valid] = 0
    return t


def _disc_tophat(hn: np.ndarray, length_px: float) -> np.ndarray:
    """``hn`` minus its grey opening by a disc ``length_px`` wide (on an area-averaged copy, so
    that the disc is ~25 px; the opening brought back to full size and capped by ``hn``): the
    height over the paint's lowest envelope, for everything narrower than the disc (um)."""
    m, n = hn.shape
    f = max(1, int(length_px // 25))
    small = hn
    if f > 1:
        small = cv2.resize(hn, (max(n // f, 1), max(m // f, 1)), interpolation=cv2.INTER_AREA)
    d = max(3, int(round(length_px / f)) | 1)
    se = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (d, d))
    opened = cv2.morphologyEx(small, cv2.MORPH_OPEN, se, borderType=cv2.BORDER_REFLECT)
    if f > 1:
        opened = np.minimum(cv2.resize(opened, (n, m), interpolation=cv2.INTER_LINEAR), hn)
    return (hn - opened).astype(np.float32)


@numba.njit(nogil=True, cache=True)
def _flood_beside(h, t, seeds, need, length, width, max_area, floor, out):  # pragma: no cover - compiled
    """:func:`_beside_long`'s floods, in place on ``out`` (a copy of ``t``). Returns how many
    seeds were raised.

    From each seed (flat indices, highest first), a priority flood (4-connected, highest
    boundary pixel first) visits the level sets of ``h`` containing it in decreasing level. It
    gives up on the seed when the visited set is ``width`` wide before it lies ``need`` below
    the seed (texture, a crest: not a small compact object), or when it covers ``max_area``
    (larger than any protrusion) before it is long. It stops when the visited set's extent
    (mirrored at the image borders, as :func:`_compact_relief` pads the image) reaches
    ``length``: the level it has fallen to, ``lam``, is where the seed's level set becomes
    long, the exact diameter opening at the seed. The seed's own hill is what the flood visited
    before it first climbed, over a saddle, above the seed or more than ``floor`` above that
    saddle. When the seed stands ``need`` above ``lam`` and the block maxima gave its hill no
    relief (``t`` below ``floor`` wherever the hill stands ``floor`` above ``lam``), those pixels
    of the hill get ``h - lam``: the exact compact relief (tested against
    :func:`skimage.morphology.diameter_opening`); not when a pixel of the hill that high lies on
    the image's border."""
    m, n = h.shape
    hf = h.ravel()
    tf = t.ravel()
    of = out.ravel()
    region = np.empty(max_area + 1, np.int64)
    stamp = np.full(m * n, -1, np.int32)
    done = np.zeros(m * n, np.bool_)
    raised = 0
    for s in range(seeds.size):
        p0 = seeds[s]
        if done[p0]:
            continue
        top = hf[p0]
        heap = [(-np.float64(top), np.int64(p0))]      # heapq is a min-heap: minus the level
        stamp[p0] = s
        r0 = p0 // n
        c0 = p0 - r0 * n
        rmin, rmax, cmin, cmax = r0, r0, c0, c0
        cnt = 0
        own = -1
        run_min = top
        lam = np.nan
        while len(heap) > 0:
            negv, i = heapq.heappop(heap)
            v = -negv
            r = i // n
            c = i - r * n
            run_min = min(run_min, v)
            if own < 0 and (v > top or v > run_min + floor):
                own = cnt
            r_lo, r_hi, c_lo, c_hi = min(rmin, r), max(rmax, r), min(cmin, c), max(cmax, c)
            # extent with the image mirrored at its borders, as _compact_relief pads it: a
            # set touching a border is as long as itself and its mirror image
            er = r_hi - r_lo + 1
            if r_lo == 0:
                er = max(er, 2 * (r_hi + 1))
            if r_hi == m - 1:
                er = max(er, 2 * (m - r_lo))
            ec = c_hi - c_lo + 1
            if c_lo == 0:
                ec = max(ec, 2 * (c_hi + 1))
            if c_hi == n - 1:
                ec = max(ec, 2 * (n - c_lo))
            ext = max(er, ec)
            if ext >= length:
                lam = run_min
                break
            if ext >= width and top - run_min < need[s]:
                break
            if cnt >= max_area:
                break
            region[cnt] = i
            cnt += 1
            rmin, rmax, cmin, cmax = r_lo, r_hi, c_lo, c_hi
            for d in range(4):
                if (d == 0 and r == 0) or (d == 1 and r == m - 1) or (d == 2 and c == 0) or \
                        (d == 3 and c == n - 1):
                    continue
                j = i - n if d == 0 else (i + n if d == 1 else (i - 1 if d == 2 else i + 1))
                if stamp[j] != s:
                    stamp[j] = s
                    heapq.heappush(heap, (-np.float64(hf[j]), np.int64(j)))
        if lam != lam or top - lam < need[s]:
            continue
        if own >= 0:
            cnt = own
        ok = True
        for q in range(cnt):
            j = region[q]
            if hf[j] - lam < floor:
                continue
            r = j // n
            c = j - r * n
            # relief from the blocks already, or cut by the image's edge (a stroke leaving it?)
            if tf[j] >= floor or r == 0 or r == m - 1 or c == 0 or c == n - 1:
                ok = False
                break
        if not ok:
            continue
        raised += 1
        for q in range(cnt):
            j = region[q]
            if hf[j] - lam >= floor:
                of[j] = max(of[j], hf[j] - lam)
                done[j] = True
    return raised


def _beside_long(surf: Surface, valid: np.ndarray, th: Thresholds, p: DetectionParams) -> np.ndarray:
    """The compact relief with the small objects the block maxima joined to a long neighbour.

    :func:`_compact_relief` opens ``f x f`` block maxima (``f = L / 16``, 5 px at 15 um per
    pixel), so a protrusion in the block next to a stroke's or a crack lip's is joined to it and
    its level sets are taken as long: it gets no relief (a 90 um mesa 22 um high, 3 px from a
    stroke, gets 0.7 um). Here the exact level sets decide, around the objects the blocks can
    hide: the local maxima of the height (over 3 x 3 px: a dome within 2 px of a taller
    neighbour's flank is one, not over 5 x 5) with no compact relief (below the
    relief threshold) that stand ``need`` above the paint's lowest envelope (the disc top-hat,
    :func:`_disc_tophat`), ``need`` being ``beside_long_fraction`` of that height and at least
    twice the relief threshold. A priority flood from each (:func:`_flood_beside`) falls through
    the level sets containing it until they reach ``L``; a seed whose own hill stands ``need``
    above that level, and which the blocks gave no relief, gets its exact compact relief there.
    A bump on a stroke already has its relief from the blocks and is left alone; a stroke's
    crest or the paint's texture widens past ``3 f + 2`` px before it has fallen ``need``, which
    bounds the cost (0.17 s at 4000 x 3000 with 5 x 5 seeds at 0.3). A hill that reaches the
    image's edge is left as it was: cut by the edge, a ripple crest of a stroke that leaves the
    image is as compact as a protrusion (the edge of ``valid`` inside the image is not an edge).
    Hand-written: the exact diameter opening of a whole 1600 x 1200 image
    (:func:`skimage.morphology.max_tree`) takes 5 s, and no library floods from chosen seeds
    only. ``beside_long_fraction`` 0 leaves the compact relief as it is, as does ``f`` = 1 (the
    blocks are then the pixels: the relief is exact already)."""
    t = surf.relief
    f = _block_factor(surf.length_px)
    if p.beside_long_fraction <= 0 or f == 1:
        return t
    hn = np.ascontiguousarray(surf.height, dtype=np.float32)
    peak = hn >= cv2.dilate(hn, np.ones((3, 3), np.uint8), borderType=cv2.BORDER_REPLICATE)
    need_all = np.maximum(2.0 * th.relief_um, p.beside_long_fraction * surf.disc)
    seeds = np.flatnonzero(peak & valid & (t < th.relief_um) & (surf.disc >= need_all))
    if not seeds.size:
        return t
    seeds = seeds[np.argsort(-hn.ravel()[seeds], kind="stable")]
    out = t.copy()
    max_area = int(math.pi / 4 * th.max_w ** 2)
    n = _flood_beside(hn, t, seeds.astype(np.int64), need_all.ravel()[seeds].astype(np.float32),
                      int(math.ceil(surf.length_px)), 3 * f + 2, max_area, float(th.relief_um), out)
    out[~valid] = 0
    logger.debug("beside_long: %d of %d seeds raised", n, seeds.size)
    return out


def _surface(h: np.ndarray, valid: np.ndarray, px: float, p: DetectionParams) -> Surface:
    """Noise, weave and compact relief of the height (see the module docstring, steps 1-2)."""
    fill = float(np.median(h[valid])) if not valid.all() else 0.0    # no pixel to fill: 0.3 s
    h0 = np.where(valid, h, fill).astype(np.float32)
    noise = _noise_sigma(h0, valid)
    s = p.smooth_um / px
    if s >= 0.3:
        hs = cv2.GaussianBlur(h0, (0, 0), s, borderType=cv2.BORDER_REFLECT)
        k1 = cv2.getGaussianKernel(2 * int(math.ceil(4 * s)) + 1, s)
        noise_s = noise * float(np.sum(k1 ** 2))  # white noise through the separable kernel
    else:
        hs, noise_s = h0, noise
    hn, weave = _remove_weave(hs, px, p)
    length = 1.3 * p.max_width_um / px + 2
    return Surface(raw=h0, height=hn, relief=_compact_relief(hn, valid, length),
                   disc=_disc_tophat(hn, length), noise_um=noise, noise_smoothed_um=noise_s,
                   weave=weave, length_px=length)


def _thresholds(surf: Surface, px: float, p: DetectionParams) -> Thresholds:
    relief = max(p.min_dynamic_um, p.dynamic_k * surf.noise_smoothed_um)
    slope = max(2 * p.min_relief_ratio, p.weave_slope_k * surf.weave.slope_rms)
    return Thresholds(relief, slope, p.min_width_um / px, p.max_width_um / px)


# --------------------------------------------------------------------------------------------
# Cues
# --------------------------------------------------------------------------------------------


def _label_max(values: np.ndarray, labels: np.ndarray, n: int) -> np.ndarray:
    """Maximum of ``values`` per label 1..n (-inf for an empty label), via ``np.maximum.at``.

    ``scipy.ndimage.maximum`` with an index sorts every labelled pixel; this is O(pixels).
    """
    out = np.full(n + 1, -np.inf)
    sel = labels > 0
    np.maximum.at(out, labels[sel], values[sel])
    return out[1:]


def _label_mean(values: np.ndarray, labels: np.ndarray, n: int, default: float = 0.0) -> np.ndarray:
    """Mean of ``values`` per label 1..n (``default`` for an empty label), via ``np.bincount``."""
    sel = labels > 0
    cnt = np.bincount(labels[sel], minlength=n + 1)[1:n + 1]
    tot = np.bincount(labels[sel], weights=values[sel].astype(np.float64), minlength=n + 1)[1:n + 1]
    return np.where(cnt > 0, tot / np.maximum(cnt, 1), default)


def _peak_markers(t: np.ndarray, th: Thresholds, p: DetectionParams) -> tuple:
    """Peaks of the compact relief: at least ``relief_um`` high, and ``split_fraction`` above
    the saddle to any higher peak (``h_maxima`` of ``log(t + relief_um)``: a relative dynamic,
    so a crater's rim or a mesa's rippled top stays one peak and touching protrusions split).
    Per raised area (a path to a higher peak over a saddle above half the threshold stays
    inside it), which is much cheaper than the full-image reconstruction. With
    ``weak_split_fraction`` below ``split_fraction``, the peaks whose dynamic lies between the
    two are returned too, flagged weak (:func:`_weak_splits` decides on them).
    Returns (markers, n, weak: per id 1..n whether the peak is weak, index 0 unused)."""
    m, n = t.shape
    low = t >= 0.5 * th.relief_um
    comp, ncomp = ndi.label(low, structure=np.ones((3, 3)))
    markers = np.zeros((m, n), np.int32)
    weak = [False]
    if not ncomp:
        return markers, 0, np.asarray(weak)
    top = _label_max(t, comp, ncomp)
    dyn = -math.log(1.0 - p.split_fraction)
    use_weak = 0 < p.weak_split_fraction < p.split_fraction
    dyn_w = -math.log(1.0 - p.weak_split_fraction) if use_weak else 0.0
    k_all = 0
    for k_comp, sl in enumerate(ndi.find_objects(comp)):
        if top[k_comp] < th.relief_um:
            continue
        inside = comp[sl] == k_comp + 1
        sub = np.where(inside, np.log(t[sl].astype(np.float64) + th.relief_um), -1.0)
        hm = h_maxima(sub, dyn).astype(bool) & inside & (t[sl] >= th.relief_um)
        lab, k = ndi.label(hm, structure=np.ones((3, 3)))
        n_w = 0
        if dyn_w:                                   # the weak peaks: numbered after the strong
            hw = h_maxima(sub, dyn_w).astype(bool) & inside & (t[sl] >= th.relief_um)
            lw, kw = ndi.label(hw, structure=np.ones((3, 3)))
            strong = np.zeros(kw + 1, bool)
            strong[lw[hm]] = True                   # the strong peaks' own components
            strong[0] = True
            n_w = kw + 1 - int(np.count_nonzero(strong))
            lut = np.zeros(kw + 1, np.int32)
            lut[~strong] = np.arange(k + 1, k + 1 + n_w)
            lab = np.where(strong[lw], lab, lut[lw])
        weak.extend([False] * k + [True] * n_w)
        k += n_w
        if k:
            markers[sl][lab > 0] = lab[lab > 0] + k_all
            k_all += k
    return markers, k_all, np.asarray(weak)


#: A weak peak (:func:`_weak_splits`) at most this fraction of the relief of the tallest peak it
#: touches stays its own protrusion: a small dome on a taller one's flank. Lumps of one object
#: (a crater's rim, a pile's ripples) are of about the same height and stay one. The shoulder
#: cue (:func:`_shoulder_markers`) holds a shoulder to the same fraction of its basin's peak.
WEAK_HOST_RATIO = 0.75


def _weak_splits(t: np.ndarray, ws: np.ndarray, weak: np.ndarray, p: DetectionParams) -> np.ndarray:
    """Which weak peaks (:func:`_peak_markers`) stay protrusions of their own.

    A weak peak stands between ``weak_split_fraction`` and ``split_fraction`` of its relief
    above the saddle to a higher one: a cluster member on a taller neighbour's flank (60-100 um
    wide, its saddle 1-2 um deep), or one of the lumps of a crater's rim or of the ripples of a
    pile of paint. It is kept when its relief is at most :data:`WEAK_HOST_RATIO` of the tallest
    basin of ``ws`` it touches (a small member on a taller one: the lumps of one object are of
    a height) and its basin and the tallest basin it touches are not elongated together (the
    minor axis of their second moments at least ``ridge_axis_ratio`` of the major: two touching
    domes are >= 0.5, a rippled pile is a ridge; a member between two neighbours in a row is
    judged with the taller one alone, the row of three being 3x longer than wide). Hand-written:
    no library splits on a dynamic under a shape condition. Returns a boolean per id 0..n
    (index 0 unused): kept."""
    keep = ~weak
    n = weak.size - 1
    if n < 1 or not weak.any():
        return keep
    pairs = []                                  # basins side by side (8-connected), both ways
    for a, b in ((ws[:, :-1], ws[:, 1:]), (ws[:-1], ws[1:]), (ws[:-1, :-1], ws[1:, 1:]),
                 (ws[:-1, 1:], ws[1:, :-1])):
        sel = (a > 0) & (b > 0) & (a != b)
        pairs += [np.column_stack([a[sel], b[sel]]), np.column_stack([b[sel], a[sel]])]
    pairs = np.unique(np.concatenate(pairs), axis=0)        # sorted by the first basin
    start = np.searchsorted(pairs[:, 0], np.arange(n + 2))
    top = np.concatenate([[0.0], _label_max(t, ws, n)])
    boxes = ndi.find_objects(ws, max_label=n)
    is_g = np.zeros(n + 1, bool)
    for q in np.flatnonzero(weak[1:]) + 1:
        group = np.concatenate([[q], pairs[start[q]:start[q + 1], 1]])
        if boxes[q - 1] is None or top[q] > WEAK_HOST_RATIO * top[group].max():
            keep[q] = False
            continue
        group = np.array([q, group[1:][np.argmax(top[group[1:]])]]) if group.size > 1 else group
        sls = [boxes[g - 1] for g in group if boxes[g - 1] is not None]
        r0, r1 = min(s[0].start for s in sls), max(s[0].stop for s in sls)
        c0, c1 = min(s[1].start for s in sls), max(s[1].stop for s in sls)
        is_g[group] = True
        rr, cc = np.nonzero(is_g[ws[r0:r1, c0:c1]])
        is_g[group] = False
        ev = np.linalg.eigvalsh(np.cov(np.vstack([rr, cc]))) if rr.size > 2 else np.ones(2)
        keep[q] = ev[1] <= 0 or math.sqrt(max(ev[0], 0.0) / ev[1]) >= p.ridge_axis_ratio
    return keep


def _shoulder_markers(t: np.ndarray, ws: np.ndarray, markers: np.ndarray, th: Thresholds,
                      px: float, p: DetectionParams, disc: np.ndarray = None) -> tuple:
    """Markers of small protrusions that are only a shoulder of a taller neighbour, and the
    curvature they were found on.

    A dome of width ``w`` on the flank of a taller protrusion has no maximum of the height of
    its own (or one with no saddle ``split_fraction`` below it), but its curvature does: minus
    the Laplacian of Gaussian of the compact relief at sigma ``w / (2 sqrt 2)`` (the scale at
    which a paraboloid of that width responds most) has a maximum on it. Kept: maxima whose
    dynamic (``h_maxima``: how far the curvature drops before a higher peak) exceeds
    ``shoulder_k`` x the curvature's noise (a robust MAD over the image) and the curvature
    ``4 relief_um / (w / 2)^2`` of a paraboloid ``w`` wide and the relief threshold high,
    where both eigenvalues of the Hessian are negative with a ratio >= ``shoulder_isotropy``
    (curved down all round: not a mesa's or a crater's rim, not a stroke's crest), at least
    the relief threshold high and ``w / 2 + 1`` px from every height marker, inside a basin; at most
    :data:`WEAK_HOST_RATIO` of the basin's peak high (a smaller protrusion on a taller one's
    flank: a lump of a crater's rim or of a mesa's edge stands near the peak's height), and,
    given the disc top-hat ``disc``, on no long structure (the mean of ``disc - t`` over it
    below the larger of the relief threshold and a quarter of its height: the measure of
    :func:`_stroke_slope`, though its height here is the compact relief at the curvature peak,
    the neighbour's flank under it included; a stroke's lump is no protrusion's shoulder). Hand-
    written because no library detects blobs inside another's footprint: skimage's
    ``blob_log`` finds scale-space maxima over the whole image, without the footprint, the
    isotropy or a dynamic. Returns (markers with the shoulders added, n, curvature)."""
    n_h = int(markers.max())
    if p.shoulder_width_um <= 0 or not n_h:
        return markers, n_h, None
    w = p.shoulder_width_um / px
    sigma = w / (2.0 * math.sqrt(2.0))
    curv = _log_curvature(t, sigma)
    noise = 1.4826 * float(np.median(np.abs(curv - np.median(curv))))
    dyn = max(p.shoulder_k * noise, 4.0 * th.relief_um / (0.5 * w) ** 2)
    inside = ws > 0
    if not inside.any():
        return markers, n_h, curv
    # A shoulder stands at least relief_um high and at most WEAK_HOST_RATIO of its basin's
    # peak, so only raised areas (touching basins) holding a basin that tall can have one: the
    # curvature's maxima are sought on their crops alone and its Hessian is measured at those
    # maxima alone (over the whole image the cue cost 17-21 s at 4000 x 3000, mostly
    # h_maxima; so, about 1 s: docs/benchmarks.md). Each crop's margin holds every marker
    # within w / 2 + 1 px, and the pixels outside the raised area take the value they have on
    # the whole image (the lowest curvature inside any basin), so the maxima and their
    # dynamics are the whole image's (test_shoulder_markers_on_crops_are_the_whole_images).
    host = np.concatenate([[0.0], _label_max(t, ws, int(ws.max()))])
    area, n_area = ndi.label(inside, structure=np.ones((3, 3)))
    able = np.zeros(n_area + 1, bool)
    able[area[(host >= th.relief_um / WEAK_HOST_RATIO)[ws] & inside]] = True
    fill = float(curv[inside].min())
    pad = int(math.ceil(w / 2.0 + 2.0))
    m, n = t.shape
    hm = np.zeros(t.shape, bool)
    far = np.zeros(t.shape, bool)
    for i, sl in enumerate(ndi.find_objects(area)):
        if not able[i + 1]:
            continue
        crop = (slice(max(sl[0].start - pad, 0), min(sl[0].stop + pad, m)),
                slice(max(sl[1].start - pad, 0), min(sl[1].stop + pad, n)))
        own = area[crop] == i + 1
        c = curv[crop]
        peaks = (h_maxima(np.where(own, c, fill), dyn) > 0) & own & (t[crop] >= th.relief_um)
        hm[crop] |= peaks
        far[crop] |= own & (_edt(markers[crop] == 0) >= w / 2.0 + 1.0)
    hm[hm] = _isotropy_at(curv, *np.nonzero(hm)) >= p.shoulder_isotropy
    lab, k = ndi.label(hm, structure=np.ones((3, 3)))
    if not k:
        return markers, n_h, curv
    ok = np.zeros(k + 1, bool)
    ok[np.unique(lab[hm & far])] = True
    touch = np.unique(lab[hm & ~far])
    ok[touch] = False
    ok[0] = False
    # a shoulder is a smaller protrusion on a taller one's flank: at most WEAK_HOST_RATIO of the
    # basin's peak (a lump of a crater's rim or of a mesa's edge stands near the peak's height)
    top = np.concatenate([[0.0], _label_max(t, lab, k)])
    host_of = np.zeros(k + 1)
    np.maximum.at(host_of, lab[hm], host[ws[hm]])
    ok &= top <= WEAK_HOST_RATIO * host_of
    if disc is not None:        # not on a long structure (a stroke's lump), as _stroke_slope's
        under = np.concatenate([[0.0], _label_mean(disc - t, lab, k)])
        ok &= ~_on_long_structure(under, top, th)
    keep = ok[lab]
    lut = np.zeros(k + 1, np.int32)
    lut[ok] = np.arange(n_h + 1, n_h + 1 + int(ok.sum()), dtype=np.int32)
    out = markers.copy()
    out[keep] = lut[lab[keep]]
    return out, int(out.max()), curv


def _gaussian_kernels(sigma: float) -> tuple:
    """The Gaussian and its first and second derivatives at ``sigma`` px, radius
    ``int(4 sigma + 0.5)``: the kernels of ``scipy.ndimage.gaussian_filter1d`` (orders 0-2,
    its default truncation), as 1-D float64 arrays."""
    r = int(4.0 * sigma + 0.5)
    x = np.arange(-r, r + 1, dtype=np.float64)
    g = np.exp(-0.5 * x * x / sigma ** 2)
    g /= g.sum()
    return g, -x / sigma ** 2 * g, (x * x / sigma ** 4 - 1.0 / sigma ** 2) * g


def _log_curvature(t: np.ndarray, sigma: float) -> np.ndarray:
    """Minus the Laplacian of Gaussian of ``t`` (float64): ``-scipy.ndimage.gaussian_laplace(t,
    sigma)`` to rounding (its kernels and ``reflect`` border) by OpenCV's separable filter,
    ~4x faster (0.27 s against 1.0 s at 4000 x 3000)."""
    g, _, d2 = _gaussian_kernels(sigma)
    t64 = t.astype(np.float64)
    return -(cv2.sepFilter2D(t64, cv2.CV_64F, g, d2, borderType=cv2.BORDER_REFLECT)
             + cv2.sepFilter2D(t64, cv2.CV_64F, d2, g, borderType=cv2.BORDER_REFLECT))


def _isotropy_at(curv: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """At the given pixels, the ratio of the two eigenvalues of the Hessian of ``curv`` (its
    Gaussian derivatives at sigma 1 px, as ``scipy.ndimage.gaussian_filter(curv, 1, order=...)``
    with its ``reflect`` border and radius 4): ``lam_hi / lam_lo`` where both are negative
    (curved down all round: 1 for a round blob, near 0 for a crest), else 0. The blob of
    curvature a dome makes, whatever slope or curvature of its neighbour it sits on, is curved
    down all round; a rim or a crest only across. Hand-written as sums over each pixel's 9 x 9
    neighbourhood because only the curvature's maxima need it: the three filters over the
    whole image cost ~1.5 s at 4000 x 3000."""
    g, d1, d2 = _gaussian_kernels(1.0)
    def reflect(i, size):       # scipy's "reflect" border (d c b a | a b c d | d c b a), any size
        i = np.mod(i, 2 * size)
        return np.where(i >= size, 2 * size - 1 - i, i)

    off = np.arange(-(g.size // 2), g.size // 2 + 1)
    rr = reflect(rows[:, None] + off, curv.shape[0])
    cc = reflect(cols[:, None] + off, curv.shape[1])
    patch = curv[rr[:, :, None], cc[:, None, :]]
    hrr = np.einsum("pij,i,j->p", patch, d2, g)
    hcc = np.einsum("pij,i,j->p", patch, g, d2)
    hrc = np.einsum("pij,i,j->p", patch, d1, d1)   # both odd kernels flipped: the signs cancel
    half_tr, det_d = 0.5 * (hrr + hcc), np.sqrt(0.25 * (hrr - hcc) ** 2 + hrc ** 2)
    lam_hi, lam_lo = half_tr + det_d, half_tr - det_d          # lam_lo <= lam_hi
    return np.where(lam_hi < 0, lam_hi / np.minimum(lam_lo, -1e-12), 0.0)


def _height_cue(t: np.ndarray, th: Thresholds, px: float, p: DetectionParams,
                disc: np.ndarray = None) -> tuple:
    """Compact footprints of the compact-relief peaks: watershed of ``-t`` from the markers
    (splits touching clusters), then the part of each basin above ``footprint_fraction`` of its
    peak that is connected to the marker. A basin holding shoulder markers
    (:func:`_shoulder_markers`) is split again by a watershed of minus the curvature, so the
    shoulder gets the part of the basin its own curvature encloses; ``disc`` (the disc top-hat)
    goes to :func:`_shoulder_markers` for its long-structure test (None: no such test).
    Returns (labels, markers, n, n_peaks): labels above ``n_peaks`` are shoulders."""
    markers, n_h, weak = _peak_markers(t, th, p)
    if not n_h:
        return np.zeros(t.shape, np.int32), markers, 0, 0
    floor = p.footprint_fraction * th.relief_um
    ws = watershed(-t, markers, mask=(t >= floor) | (markers > 0))
    if weak.any():
        keep = _weak_splits(t, ws, weak, p)
        if not keep[1:].all():                      # renumber the markers kept, 1..n
            markers = np.where(keep, np.cumsum(keep) - 1, 0).astype(np.int32)[markers]
            n_h = int(markers.max())
            ws = watershed(-t, markers, mask=(t >= floor) | (markers > 0))
    n_peaks = n_h
    markers, n_h, curv = _shoulder_markers(t, ws, markers, th, px, p, disc)
    if n_h > n_peaks:
        split = np.zeros(n_peaks + 1, bool)
        split[np.unique(ws[markers > n_peaks])] = True
        split[0] = False
        region = split[ws]
        sub = watershed(-curv, np.where(region, markers, 0), mask=region)
        ws = np.where(region, sub, ws)
    peak = _label_max(t, ws, n_h)
    cut = np.concatenate([[np.inf], p.footprint_fraction * peak])
    return _seeded(ws, (t >= cut[ws]) & (ws > 0), markers), markers, n_h, n_peaks


def _seeded(ws: np.ndarray, foot: np.ndarray, markers: np.ndarray) -> np.ndarray:
    """``ws`` where ``foot`` is connected to a marker pixel, else 0."""
    parts, _ = ndi.label(foot, structure=np.ones((3, 3)))
    seeded = np.zeros(parts.max() + 1, bool)
    seeded[parts[markers > 0]] = True
    seeded[0] = False
    return np.where(seeded[parts], ws, 0).astype(np.int32)


def _median(x: np.ndarray) -> float:
    """``np.median`` of a 1-D array by ``np.partition`` (the same value, without ``np.median``'s
    per-call overhead: the numpy plane fit calls it ~10 times per footprint)."""
    n = x.size
    part = np.partition(x, [(n - 1) // 2, n // 2])
    return 0.5 * (part[(n - 1) // 2] + part[n // 2])


def _edt(mask: np.ndarray) -> np.ndarray:
    """Euclidean distance of each True pixel to the nearest False one (float32): OpenCV's exact
    transform (``DIST_MASK_PRECISE``), the values of ``scipy.ndimage.distance_transform_edt``
    at a fraction of its cost; scipy's when there is no False pixel."""
    if mask.all():
        return ndi.distance_transform_edt(mask).astype(np.float32)
    return cv2.distanceTransform(mask.astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)


def _expand_labels(lab: np.ndarray, distance: float) -> np.ndarray:
    """:func:`skimage.segmentation.expand_labels` (the same values) computed per group of labels
    in its own crop instead of one feature transform over the whole image.

    A pixel within ``distance`` of a label has all its labels within ``distance`` in the same
    group (labels whose ``distance``-neighbourhoods can touch: the components of the labels
    dilated by a square of side ``2 ceil(distance) + 1``), so each group's crop holds every
    label that can reach its pixels. At 4000 x 3000 with a few thousand small candidates the
    crops cover a tenth of the image (``scripts/benchmark_detection_speed.py --profile 40``:
    1.5 s per call over the whole image). Tested against skimage's in ``tests/test_detect.py``."""
    r = int(math.ceil(distance))
    if r < 1 or not lab.any():
        return lab.copy()
    side = 2 * r + 1
    reach = cv2.dilate((lab > 0).astype(np.uint8), np.ones((side, side), np.uint8),
                       borderType=cv2.BORDER_CONSTANT, borderValue=0)
    grp, _ = ndi.label(reach, structure=np.ones((3, 3)))
    out = np.zeros_like(lab)
    for g, sl in enumerate(ndi.find_objects(grp)):
        own = grp[sl] == g + 1
        out[sl][own] = expand_labels(np.where(own, lab[sl], 0), distance=distance)[own]
    return out


def _holes(mask: np.ndarray) -> tuple:
    """The holes of ``mask`` labelled 1..k, as ``ndimage.label(fill_holes(mask) & ~mask)``
    (4-connected, numbered in raster order of their first pixel): the background's components
    that do not reach the border, renumbered, from one labelling of the background."""
    bg, n_bg = ndi.label(~mask)
    inner = np.ones(n_bg + 1, bool)
    inner[np.concatenate([bg[0], bg[-1], bg[:, 0], bg[:, -1]])] = False
    inner[0] = False
    lut = np.zeros(n_bg + 1, np.int32)
    lut[inner] = np.arange(1, int(inner.sum()) + 1, dtype=np.int32)
    return lut[bg], int(inner.sum())


def _robust_plane(rows, cols, values):
    """Least-squares plane ``a + b row + c col`` refitted without the samples beyond 2.5 robust
    sigmas (a neighbouring bump or a crack in the surround); a constant (median) with fewer than
    8 samples. Returns a callable of (rows, cols).

    The fit is :func:`_robust_plane_kernel` (compiled); samples on one line (a singular system)
    go to :func:`_robust_plane_numpy`, whose least squares take the minimum-norm plane."""
    values = np.asarray(values, np.float64)
    if len(values) < 8:
        med = float(_median(values)) if len(values) else 0.0
        return lambda r, c: np.full(np.shape(r), med)
    rows, cols = np.asarray(rows, np.float64), np.asarray(cols, np.float64)
    coef, r0, c0, ok = _robust_plane_kernel(rows, cols, values)
    if not ok:
        return _robust_plane_numpy(rows, cols, values)
    return lambda r, c: coef[0] + coef[1] * (r - r0) + coef[2] * (c - c0)


def _robust_plane_numpy(rows, cols, values):
    """:func:`_robust_plane` in numpy (the reference of the compiled kernel, and its fallback for
    samples on one line): least squares in coordinates centred on the samples."""
    med = float(_median(values)) if len(values) else 0.0
    if len(values) < 8:
        return lambda r, c: np.full(np.shape(r), med)
    r0, c0 = float(np.mean(rows)), float(np.mean(cols))
    a = np.column_stack([np.ones(len(values)), rows - r0, cols - c0])
    keep = np.ones(len(values), bool)
    coef = np.array([med, 0.0, 0.0])
    for _ in range(3):
        if keep.sum() < 8:
            break
        coef, *_ = np.linalg.lstsq(a[keep], values[keep], rcond=None)
        res = values - a @ coef
        centre = _median(res[keep])
        spread = 1.4826 * _median(np.abs(res[keep] - centre)) + 1e-6
        new = np.abs(res - centre) <= 2.5 * spread
        if np.array_equal(new, keep):
            break
        keep = new
    return lambda r, c: coef[0] + coef[1] * (r - r0) + coef[2] * (c - c0)


@numba.njit(nogil=True, cache=True)
def _robust_plane_kernel(rows, cols, values):  # pragma: no cover - compiled
    """The robust plane fit of :func:`_robust_plane_numpy`, compiled.

    Hand-written because the fits are many and small (two per group of footprints, 1500 at
    4000 x 3000, a few hundred samples each), where numpy's per-call overhead (lstsq, medians,
    masks: ~0.6 ms per fit on a loaded core) was a quarter of the footprints' refinement. The
    normal equations in centred coordinates, solved by Gaussian elimination with partial
    pivoting. Returns (coefficients, row centre, column centre, ok); ok is False when the
    system is singular (samples on one line)."""
    n = values.size
    r0, c0 = rows.mean(), cols.mean()
    dr, dc = rows - r0, cols - c0
    coef = np.zeros(3)
    coef[0] = np.median(values)
    keep = np.ones(n, np.bool_)
    for _ in range(3):
        if keep.sum() < 8:
            break
        g = np.zeros((3, 4))                   # the normal equations, augmented
        for i in range(n):
            if keep[i]:
                x = (1.0, dr[i], dc[i])
                for j in range(3):
                    for k in range(3):
                        g[j, k] += x[j] * x[k]
                    g[j, 3] += x[j] * values[i]
        for j in range(3):                     # elimination with partial pivoting
            piv = j
            for k in range(j + 1, 3):
                if abs(g[k, j]) > abs(g[piv, j]):
                    piv = k
            if g[piv, j] == 0.0:
                return coef, r0, c0, False
            for k in range(4):
                g[j, k], g[piv, k] = g[piv, k], g[j, k]
            for k in range(j + 1, 3):
                f = g[k, j] / g[j, j]
                for q in range(j, 4):
                    g[k, q] -= f * g[j, q]
        for j in range(2, -1, -1):
            acc = g[j, 3]
            for k in range(j + 1, 3):
                acc -= g[j, k] * coef[k]
            coef[j] = acc / g[j, j]
        res = values - (coef[0] + coef[1] * dr + coef[2] * dc)
        centre = np.median(res[keep])
        spread = 1.4826 * np.median(np.abs(res[keep] - centre)) + 1e-6
        new = np.abs(res - centre) <= 2.5 * spread
        if np.array_equal(new, keep):
            break
        keep = new
    return coef, r0, c0, True


def _local_footprints(hn, hl, markers, t, valid, th: Thresholds, p: DetectionParams) -> tuple:
    """Re-draw the height footprints over a robust local plane through their surround.

    The compact relief of a protrusion on a slope (a cupped island, the flank of a stroke) is
    only the part above where it joins the slope uphill. Per group of touching footprints
    (:func:`_refine_group`): a plane through the ring around the group (outside every other
    candidate), the relief ``d`` of the height over it, a watershed of ``-d`` from the group's
    markers, and each member's footprint where ``d`` exceeds ``footprint_fraction`` of its peak;
    twice, the second time around the new footprints. A member keeps its compact footprint and
    relief when the new one is not closed within twice its compact radius (+ 2 px) of its peak:
    then the relief over the plane continues into a long structure (a crack lip, a stroke) that
    the plane does not follow. Returns (labels, relief per label 1..n)."""
    n_h = int(markers.max())
    out = hl.copy()
    relief = np.maximum(_label_max(t, hl, n_h), 0)
    reach = 2.0 * np.sqrt(np.bincount(hl.ravel(), minlength=n_h + 1) / np.pi) + 2.0
    grp, _ = ndi.label(hl > 0, structure=np.ones((3, 3)))
    m, n = hn.shape
    for g, sl in enumerate(ndi.find_objects(grp)):
        r_eq = math.sqrt(np.count_nonzero(grp[sl] == g + 1) / math.pi)
        pad = int(math.ceil(4 * r_eq + 4))
        crop = (slice(max(sl[0].start - pad, 0), min(sl[0].stop + pad, m)),
                slice(max(sl[1].start - pad, 0), min(sl[1].stop + pad, n)))
        cur = grp[crop] == g + 1
        usable = valid[crop] & ~((out[crop] > 0) & ~cur)
        new, pk, closed = _refine_group(hn[crop], hl[crop], markers[crop], cur, usable, reach,
                                        max(2.0, 0.5 * r_eq), p)
        region = out[crop]
        members = np.flatnonzero(closed)
        is_member = np.zeros(n_h + 1, bool)             # a lookup: np.isin sorts per call
        is_member[members] = True
        change = is_member[new] | is_member[region]
        region[change] = new[change]
        relief[members - 1] = np.maximum(pk[members], 0)
    return out, relief


def _refine_group(h, hl, markers, cur, usable, reach, ring_w, p: DetectionParams) -> tuple:
    """One group of :func:`_local_footprints` in its crop. Returns (labels in the crop, peak
    relief over the plane per label id, per label id whether its new footprint is closed)."""
    members = np.unique(hl[cur])
    size = int(max(members.max(), markers.max())) + 1
    is_member = np.zeros(int(max(hl.max(), size)) + 1, bool)   # a lookup: np.isin sorts per call
    is_member[members] = True
    mk = np.where(is_member[markers], markers, 0)
    near = np.zeros(h.shape, np.int32)
    for lab_id in members:
        near[(_edt(mk != lab_id) <= reach[lab_id]) & (near == 0)] = lab_id
    rows, cols = np.arange(h.shape[0])[:, None], np.arange(h.shape[1])[None, :]
    compact = hl * is_member[hl]
    closed = np.zeros(size, bool)
    closed[members] = True
    for _ in range(2):
        dist = _edt(~cur)
        ring = (dist > 0) & (dist <= ring_w) & usable
        d = h - _robust_plane(*np.nonzero(ring), h[ring])(rows, cols)
        pk = np.full(size, -np.inf)
        np.maximum.at(pk, mk[mk > 0], d[mk > 0])
        lvl = np.where(np.isfinite(pk), p.footprint_fraction * pk, np.inf)
        ws = watershed(-d, mk, mask=((d >= lvl[members].min()) & usable) | (mk > 0))
        root = _merge_by_saddle(ws, d, pk, p.crest_fraction)
        ws, pk = root[ws], _root_max(pk, root)
        lvl = np.where(np.isfinite(pk), p.footprint_fraction * pk, np.inf)
        new = _seeded(ws, (ws > 0) & (d >= lvl[ws]), root[mk])
        outside = np.bincount(new[(new > 0) & (root[near] != new)], minlength=size)
        ok = outside <= 0.1 * np.bincount(new.ravel(), minlength=size)
        closed[members] = ok[root[members]]
        new = np.where(closed[new], new, np.where(closed[compact], 0, compact))
        cur = new > 0
    return new, pk, closed


def _root_max(values: np.ndarray, root: np.ndarray) -> np.ndarray:
    """Per id, the maximum of ``values`` over the ids sharing its root (at the root; -inf else)."""
    out = np.full(values.shape, -np.inf)
    np.maximum.at(out, root, values)
    return out


def _merge_by_saddle(ws: np.ndarray, d: np.ndarray, peak: np.ndarray, split: float) -> np.ndarray:
    """Merge touching basins of ``ws`` whose saddle (the highest pass between them in ``d``)
    lies less than ``split`` of the lower peak below it: on the relief over the local plane,
    pieces of one crest are one object, touching protrusions stay apart. Returns the root id of
    every id (the higher peak's), in decreasing saddle order as a merge tree."""
    root = np.arange(peak.size)
    pairs, values = [], []
    for a, b, da, db in ((ws[:, :-1], ws[:, 1:], d[:, :-1], d[:, 1:]),
                         (ws[:-1], ws[1:], d[:-1], d[1:])):
        sel = (a > 0) & (b > 0) & (a != b)
        pairs.append(np.column_stack([np.minimum(a[sel], b[sel]), np.maximum(a[sel], b[sel])]))
        values.append(np.minimum(da[sel], db[sel]))
    pairs, values = np.concatenate(pairs), np.concatenate(values)
    if not len(values):
        return root
    code = pairs[:, 0].astype(np.int64) * peak.size + pairs[:, 1]
    uniq, inv = np.unique(code, return_inverse=True)
    saddle = np.full(uniq.size, -np.inf)
    np.maximum.at(saddle, inv, values)
    top = peak.astype(np.float64).copy()

    def find(i):
        while root[i] != i:
            i = root[i]
        return i

    for k in np.argsort(-saddle):
        ra, rb = find(uniq[k] // peak.size), find(uniq[k] % peak.size)
        if ra != rb and saddle[k] >= (1 - split) * min(top[ra], top[rb]):
            hi, lo = (ra, rb) if top[ra] >= top[rb] else (rb, ra)
            root[lo] = hi
    return np.array([find(i) for i in range(peak.size)])


def _brightness(albedo: np.ndarray) -> np.ndarray:
    """The albedo's sum over its channels (float32): ``astype(float32).sum(axis=2)``'s values,
    added channel by channel (a reduction over an axis of 3 is 9x slower at 4000 x 3000)."""
    if albedo.ndim == 2:
        return albedo.astype(np.float32, copy=False)
    out = albedo[..., 0].astype(np.float32) + albedo[..., 1].astype(np.float32, copy=False)
    for k in range(2, albedo.shape[2]):
        out += albedo[..., k].astype(np.float32, copy=False)
    return out


def _smooth_large(img: np.ndarray, sigma_px: float) -> np.ndarray:
    """Gaussian blur with a large sigma, on an area-averaged copy (cost independent of sigma)."""
    m, n = img.shape
    f = max(1, int(sigma_px // 4))
    if f == 1:
        return cv2.GaussianBlur(img, (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)
    small = cv2.resize(img, (max(n // f, 1), max(m // f, 1)), interpolation=cv2.INTER_AREA)
    small = cv2.GaussianBlur(small, (0, 0), sigma_px / f, borderType=cv2.BORDER_REFLECT)
    return cv2.resize(small, (n, m), interpolation=cv2.INTER_LINEAR)


def _albedo_contrast(lum, valid, sigma_px, thr):
    """Relative brightness above a local background (normalised Gaussian average).

    Two passes: the second excludes pixels already brighter or darker than the threshold, so
    crowded protrusions do not raise their own background and a non-fluorescing one does not
    lower it (which would ring it with a bright halo).
    """
    lum0 = np.where(valid, lum, 0).astype(np.float32)
    w = valid.astype(np.float32)
    bg = None
    for _ in range(2):
        bg = _smooth_large(lum0 * w, sigma_px) / np.maximum(_smooth_large(w, sigma_px), 1e-6)
        w = (valid & (np.abs(lum0 - bg) <= bg * thr)).astype(np.float32)
    scale = float(np.median(lum0[valid])) if valid.any() else 1.0
    return np.where(valid, lum0 / np.maximum(bg, 1e-6 * max(scale, 1e-30)) - 1, 0).astype(np.float32)


def _disc_template(d: float) -> np.ndarray:
    """A disc of diameter ``d`` px centred in a square of side ~2d (its surround is part of it)."""
    side = max(5, int(math.ceil(2 * d)) | 1)
    c = (side - 1) / 2
    yy, xx = np.mgrid[:side, :side]
    r = np.hypot(yy - c, xx - c)
    # anti-aliased edge so that small discs stay discs
    return np.clip(d / 2 - r + 0.5, 0, 1).astype(np.float32)


def _template_match(contrast: np.ndarray, comp: np.ndarray, n: int, diameters,
                    ncc: float) -> np.ndarray:
    """Per component 1..n of ``comp``: does a disc template centred on one of its pixels reach a
    normalised correlation (TM_CCOEFF_NORMED) of ``ncc`` at one of the disc diameters?

    Diameters in turn, each only for the components no smaller disc matched. Per diameter,
    :func:`cv2.matchTemplate` runs on each such component's box widened by half the template
    (reflected at the image's border) while those crops add up to less than half the image,
    else once on the whole image: at 4000 x 3000 the components cover ~1 % of it and the whole
    image cost 0.5 s per diameter. The scores are the whole image's to float32 rounding (a few
    1e-6)."""
    m, nc = contrast.shape
    matched = np.zeros(n, bool)
    src = np.ascontiguousarray(contrast, dtype=np.float32)
    slices = ndi.find_objects(comp)
    for d in diameters:
        tpl = _disc_template(d)
        k = tpl.shape[0]
        half = k // 2
        todo = [i for i, sl in enumerate(slices) if sl is not None and not matched[i]]
        if k >= min(m, nc) or not todo:
            continue
        padded = cv2.copyMakeBorder(src, half, half, half, half, cv2.BORDER_REFLECT)
        crops = sum((slices[i][0].stop - slices[i][0].start + k)
                    * (slices[i][1].stop - slices[i][1].start + k) for i in todo)
        if crops >= 0.5 * m * nc:
            score = cv2.matchTemplate(padded, tpl, cv2.TM_CCOEFF_NORMED)
            matched |= _label_max(score, comp, n) >= ncc
            continue
        for i in todo:
            sl = slices[i]
            win = padded[sl[0].start:sl[0].stop + 2 * half, sl[1].start:sl[1].stop + 2 * half]
            score = cv2.matchTemplate(win, tpl, cv2.TM_CCOEFF_NORMED)
            matched[i] = score[comp[sl] == i + 1].max() >= ncc
    return matched


def _albedo_cue(lum, valid, px: float, th: Thresholds, p: DetectionParams) -> np.ndarray:
    """Bright components (contrast above ``albedo_contrast``) that match a disc template."""
    s = p.smooth_um / px
    fill = float(np.median(lum[valid])) if not valid.all() else 0.0    # no pixel to fill
    lum_s = np.where(valid, lum, fill).astype(np.float32)
    if s >= 0.3:
        lum_s = cv2.GaussianBlur(lum_s, (0, 0), s, borderType=cv2.BORDER_REFLECT)
    contrast = _albedo_contrast(lum_s, valid, max(2.0, 0.5 * th.max_w), p.albedo_contrast)
    raw = valid & (contrast > p.albedo_contrast)
    acomp, na = ndi.label(raw, structure=np.ones((3, 3)))
    if not na:
        return np.zeros(lum.shape, bool)
    k = max(int(p.template_scales), 1)
    diam = np.geomspace(max(th.min_w, 2.0), max(th.max_w, th.min_w * 1.01, 2.5), k)
    keep = np.concatenate([[False], _template_match(np.clip(contrast, 0, 2 * p.albedo_contrast + 0.5),
                                                    acomp, na, diam, p.template_ncc)])
    return keep[acomp]


def _long_areas(surf: Surface, valid, th: Thresholds, taken: np.ndarray) -> tuple:
    """Raised areas that the compact relief leaves out (strokes, crack lips).

    The disc top-hat (:func:`_disc_tophat`) keeps what is narrower than ``L``; what rises above
    the compact relief by the relief threshold but lies outside every compact footprint
    (``taken``) is a long structure. Returns (labels, disc top-hat in um).
    """
    raised = valid & (surf.disc - surf.relief >= th.relief_um) & ~taken
    lab, _ = ndi.label(raised, structure=np.ones((3, 3)))
    return lab.astype(np.int32), surf.disc


def _union(hl: np.ndarray, n_h: int, mask_albedo: np.ndarray, long_lab: np.ndarray,
           grow_px: float) -> tuple:
    """One label image of every candidate: height footprints (1..n_h) extended by the pixels
    of their own glow within ``grow_px`` of them (an albedo component that overlaps the
    footprint: a bright area of paint beside a protrusion that does not glow is not its
    outline), then the albedo components within ``grow_px`` of none of them, then long raised
    areas touching neither. An albedo component within ``grow_px`` of a footprint that it does
    not overlap is neither an outline nor a candidate. Returns (labels, n_albedo_only, n_long,
    the albedo components: ``mask_albedo`` labelled, 8-connected)."""
    near = _expand_labels(hl, grow_px) if n_h else hl    # nearest footprint: exact
    acomp, na = ndi.label(mask_albedo, structure=np.ones((3, 3)))
    glow = acomp
    # a footprint takes the albedo pixels of a component that overlaps it (its own glow)
    both = mask_albedo & (hl > 0)
    own = np.unique(acomp[both].astype(np.int64) * (n_h + 1) + hl[both])
    ext = mask_albedo & (hl == 0) & (near > 0)
    ok = np.isin(acomp[ext].astype(np.int64) * (n_h + 1) + near[ext], own)   # few pixels
    lab = hl.astype(np.int32, copy=True)
    lab[ext] = np.where(ok, near[ext], 0)
    joined = np.zeros(na + 1, bool)                      # a lookup: np.isin sorts the image
    joined[acomp[mask_albedo & (near > 0)]] = True       # what lies beyond grow_px is dropped
    acomp, na = ndi.label(mask_albedo & ~joined[acomp], structure=np.ones((3, 3)))
    if na:
        lab = np.where(acomp > 0, acomp + n_h, lab).astype(np.int32)
    taken = cv2.dilate((lab > 0).view(np.uint8), np.ones((3, 3), np.uint8),
                       borderType=cv2.BORDER_CONSTANT, borderValue=0).view(bool)
    touch = np.zeros(int(long_lab.max()) + 1, bool)
    touch[long_lab[taken]] = True
    keep = (long_lab > 0) & ~touch[long_lab]
    lcomp, nl = ndi.label(keep, structure=np.ones((3, 3)))
    if nl:
        lab = np.where(lcomp > 0, lcomp + n_h + na, lab).astype(np.int32)
    return lab, na, nl, glow


# --------------------------------------------------------------------------------------------
# Rejection
# --------------------------------------------------------------------------------------------


@dataclass
class Candidates:
    """Every candidate of :func:`_candidates`, before rejection."""

    labels: np.ndarray          # (M, N) int32: 1..n_h height, then albedo-only, then long areas
    n_h: int
    n_albedo: int
    n_long: int
    height: np.ndarray          # (M, N) int32 height footprints
    height_relief: np.ndarray   # (n_h,) relief of each height footprint over its local plane
    mask_albedo: np.ndarray     # (M, N) bool
    t_disc: np.ndarray          # (M, N) disc top-hat of the height (um)
    glow: np.ndarray            # (M, N) int32 components of mask_albedo (8-connected)


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
    the nearest pixel outside it (touching labels count as outside).

    Each label in its own crop, its box widened by 1 px: a label touching no other has, along
    its row and its column, an unlabelled pixel within that ring, nearer than any pixel beyond
    it, so the crop's distances are the whole image's (a whole-image transform cost 0.5 s at
    4000 x 3000 for candidates covering a tenth of it)."""
    r_in = np.full(n, -np.inf)
    touching = np.zeros(n + 1, bool)
    for a, b in ((lab[:, :-1], lab[:, 1:]), (lab[:-1], lab[1:])):
        sel = (a != b) & (a > 0) & (b > 0)
        touching[a[sel]] = touching[b[sel]] = True
    for i, s in enumerate(ndi.find_objects(lab), start=1):
        if s is None:
            continue
        sl = tuple(slice(max(k.start - 1, 0), k.stop + 1) for k in s)
        if touching[i]:
            r_in[i - 1] = _edt(np.pad(lab[sl] == i, 1)).max()
        else:
            r_in[i - 1] = _edt(lab[sl] > 0)[lab[sl] == i].max()
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
    maps of docs/benchmarks.md the ring pixels that rejected three 88-95 um protrusions lay in
    such pockets, none on a crack, while the pieces of paint the rule rejects lay on cracks all
    round. The groove is followed only below the ring's mean height (``level``): on steeply
    tilted paint a crack climbing away from the label can be cut short of ``reach_px`` and read
    as a pocket; and where the height was not measured it holds the median fill, which ends a
    groove too. Hand-written: a component's reach from an object is no library's measurement."""
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
    hp = np.pad(h.astype(np.float64), 1, mode="reflect", reflect_type="odd")  # one-sided at edges
    d_col = (hp[rr + 1, cc + 2] - hp[rr + 1, cc]) / (2 * px)
    d_row = (hp[rr + 2, cc + 1] - hp[rr, cc + 1]) / (2 * px)
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
    lab, n_h, t_disc = cand.labels, cand.n_h, cand.t_disc
    n_lab = int(lab.max())
    area_all = np.bincount(lab.ravel(), minlength=n_lab + 1)[1:]
    lbl = np.flatnonzero(area_all) + 1
    area = area_all[lbl - 1].astype(np.float64)
    eqd = np.sqrt(4 * area / np.pi)
    ring_w = max(2.0, 0.25 * th.min_w + 1)
    ring = _expand_labels(lab, ring_w) * (lab == 0)
    ring2 = ring if ring_w == 2.0 else _expand_labels(lab, 2.0) * (lab == 0)
    t = surf.relief
    relief = (_label_max(t, lab, n_lab) - _label_mean(t, ring, n_lab))[lbl - 1]
    is_h = lbl <= n_h
    relief[is_h] = cand.height_relief[lbl[is_h] - 1]
    rel_all = np.zeros(n_lab)
    rel_all[lbl - 1] = relief
    crack = _crack_fraction(lab, ring2, surf.height, rel_all, n_lab, p.crack_width_um / px,
                            th.relief_um, check_above=p.max_crack_fraction, known=left_out)[lbl - 1]
    relief_disc = (_label_max(t_disc, lab, n_lab) - _label_mean(t_disc, ring, n_lab))[lbl - 1]
    elong = area / (np.pi * _inscribed_radius(lab, n_lab)[lbl - 1] ** 2)
    holes = _hole_area(lab, n_lab)[lbl - 1]
    n_alb = np.bincount(lab[cand.mask_albedo], minlength=n_lab + 1)[lbl]
    glow_area = _glow_area(lab, n_lab, cand.glow)[lbl - 1]
    own_glow = np.where(glow_area > 0, n_alb / np.maximum(glow_area, 1), 0.0)
    major = np.zeros(lbl.size)
    ratio = np.ones(lbl.size)
    need = (eqd >= th.min_w) & (eqd <= th.max_w) & (elong <= p.ridge_elongation)
    if need.any():  # the axes only where they can decide something
        ax_major, ax_minor = _axis_lengths(lab, n_lab)
        major[need] = ax_major[lbl[need] - 1]
        ratio[need] = ax_minor[lbl[need] - 1] / np.maximum(major[need], 1e-9)
    tilt, mismatch = _normals_features(normals, surf.raw, lab, n_lab, px, left_out)
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
                             has_h=lbl <= n_h, has_a=n_alb >= np.maximum(1, 0.2 * area),
                             own_glow=own_glow,
                             crack_fraction=crack, tilt_deg=tilt[lbl - 1],
                             mismatch=mismatch[lbl - 1], unmeasured=unm)


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


def _on_long_structure(under: np.ndarray, relief: np.ndarray, th: Thresholds) -> np.ndarray:
    """Whether an object of ``relief`` stands on a long structure: the disc top-hat exceeds the
    compact relief under it (``under``, its mean) by the relief threshold and a quarter of its
    relief (the larger of the two)."""
    return under >= np.maximum(th.relief_um, 0.25 * relief)


def _stroke_slope(f: CandidateFeatures, th: Thresholds, px: float, p: DetectionParams) -> tuple:
    """The strokes' own statistics: which candidates are bumps on a long structure (a compact
    peak with a long structure under it at least the relief threshold and a quarter of its
    relief high, no albedo glow), and the least flank slope a protrusion among them must have:
    ``stroke_slope_k`` x their median flank slope (inf-free: 0 with fewer than 8 of them, then
    no candidate is tested). Returns (on_long mask, least slope)."""
    slope = f.relief / np.maximum(f.eqd * px / 2, 1e-12)
    on_long = f.has_h & ~f.has_a & _on_long_structure(f.under, f.relief, th)
    if p.stroke_slope_k <= 0 or on_long.sum() < 8:
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
    row: on the end-to-end captures of docs/benchmarks.md two weakly glowing ones 200-230 um
    wide stood 55-70 um over their surround, between crests a fifth as high. Hand-written: no
    library tests collinear, evenly spaced neighbours; the neighbours come from
    :class:`scipy.spatial.cKDTree`. Returns a mask."""
    out = np.zeros(f.lbl.size, bool)
    pop = np.flatnonzero(on_long)
    if p.ripple_reach <= 0 or pop.size < 3:
        return out
    tree = cKDTree(f.centroid[pop])
    d = f.eqd
    triples = []                                     # (middle, one end, the other end)
    cos_max = math.cos(math.radians(150.0))
    for j, near in zip(pop, tree.query_ball_point(f.centroid[pop], p.ripple_reach * d[pop])):
        q = pop[np.asarray(near, dtype=np.intp)]
        q = q[(q != j) & (d[q] >= d[j] / 1.6) & (d[q] <= 1.6 * d[j])
              & (f.relief[q] >= f.relief[j] / 2.0) & (f.relief[q] <= 2.0 * f.relief[j])]
        v = f.centroid[q] - f.centroid[j]
        r = np.hypot(v[:, 0], v[:, 1])
        q, v, r = q[r > 0], v[r > 0], r[r > 0]       # a centroid on j's own: no direction
        if q.size < 2:
            continue
        cos = (v @ v.T) / np.outer(r, r)
        ratio = r[:, None] / r[None, :]
        a, b = np.nonzero(np.triu((cos < cos_max) & (ratio <= 1.5) & (ratio >= 1 / 1.5)))
        triples += [(j, int(x), int(y)) for x, y in zip(q[a], q[b])]
    beside = {(m, e) for m, x, y in triples for e in (x, y)}     # e is beside m in a row through m
    for m, x, y in triples:
        out[m] = True
        # a row of four or more, x m y z: m is also beside y in the row (m, y, z); a row of three,
        # or another row crossing through y, keeps x
        out[x] |= (y, m) in beside
        out[y] |= (x, m) in beside
    return out


def _apply_rules(f: CandidateFeatures, th: Thresholds, px: float, p: DetectionParams,
                 on_long: np.ndarray, stroke_min: float, ripple: np.ndarray) -> np.ndarray:
    """The rule of :data:`REJECTION_RULES` each candidate fails first ("" = kept); ``on_long``,
    ``stroke_min``: :func:`_stroke_slope`; ``ripple``: :func:`_ripples`."""
    flat = (f.relief < th.relief_um) | (f.tilt_deg < 1.0)
    compact = np.where(f.relief_disc > 0, f.relief / np.maximum(f.relief_disc, 1e-12), 1.0)
    half = np.maximum(f.eqd * px / 2, 1e-12)
    slope = f.relief / half
    # the weave does not glow: a candidate whose glow is its own meets the paint's floor, its
    # relief the larger of the local one and the one over the disc opening (on a stroke's
    # curved flank the plane through its ring, or the compact relief, leaves it only its top)
    own = f.has_a & (f.own_glow >= p.own_glow_fraction)
    weave = np.where(own, np.maximum(f.relief, f.relief_disc) / half < 2 * p.min_relief_ratio,
                     slope < th.slope_min)
    tests = {
        "too_small": f.eqd < th.min_w,
        "ridge": (f.elongation > p.ridge_elongation)
                 | ((f.axis_ratio < p.ridge_axis_ratio) & (f.major * px >= p.ridge_min_length_um))
                 | (~f.has_h & (f.relief_disc >= th.relief_um) & (compact < p.ridge_compact_fraction)),
        "stroke": on_long & ((slope < stroke_min) | ripple),
        "crack": (f.hole_fraction > p.max_hole_fraction) | (f.crack_fraction > p.max_crack_fraction),
        "too_large": f.eqd > th.max_w,
        "artefact": (f.mismatch > p.max_mismatch) | (f.unmeasured > p.max_unmeasured_fraction),
        "flat_bright": flat & f.has_a & ~f.has_h,
        "weave": flat | weave,
    }
    reason = np.full(f.lbl.size, "", dtype="<U13")
    for rule in REJECTION_RULES:
        reason[tests[rule.name] & (reason == "")] = rule.name
    return reason


# --------------------------------------------------------------------------------------------
# Bumps on strokes: excess over the stroke's own continuation
# --------------------------------------------------------------------------------------------


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
    e = h - _line_opening(base, theta, max(p.along_stroke_k * r_px, 9.0))
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
        if (th.min_w <= eqd <= th.max_w and elong <= p.ridge_elongation
                and not (minor < p.ridge_axis_ratio * major
                         and major * px >= p.ridge_min_length_um)
                and peak / (eqd * px / 2) >= max(stroke_min, th.slope_min)
                and th.relief_um <= peak <= 2 * bound[j]
                and not (cracked and _outline_crack_fraction(
                    surf.height[crop], outline, peak, th.relief_um,
                    p.crack_width_um / px) > p.max_crack_fraction)
                and not (unmeasured is not None and np.count_nonzero(unmeasured[crop][outline])
                         > p.max_unmeasured_fraction * np.count_nonzero(outline))):
            region[region == k] = 0
            region[outline] = k
            kept[k], reason[j] = True, ""
    return reason, lab


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


def _finish(lab, f: CandidateFeatures, reason, shape) -> tuple:
    """Relabel the kept candidates 1..n (holes inside a kept one filled); their sources."""
    ok = reason == ""
    lut = np.zeros(int(lab.max()) + 1, np.int32)
    lut[f.lbl[ok]] = np.arange(1, int(ok.sum()) + 1, dtype=np.int32)
    labels = lut[lab]
    holes, n_holes = _holes(labels > 0)
    for k, sl in enumerate(ndi.find_objects(holes)):     # each hole from the labels around it
        sl = tuple(slice(max(s.start - 1, 0), s.stop + 1) for s in sl)
        inside = holes[sl] == k + 1
        labels[sl][inside] = expand_labels(labels[sl], distance=max(shape))[inside]
    source = np.where(f.has_h & f.has_a, "albedo+height", np.where(f.has_h, "height", "albedo"))
    return labels, source[ok].astype("<U13")


def detect_protrusions(albedo, height_um, *, pixel_size_um, normals=None, mask=None, params=None,
                       left_out=None, progress: Progress = None) -> Detection:
    """Detect metal-soap protrusions from the albedo and the height map.

    Parameters
    ----------
    albedo : (M, N, 3) or (M, N) array
        Fluorescence albedo (any global scale). Not modified.
    height_um : (M, N) array
        Height in um (median 0); NaN = unknown.
    pixel_size_um : float
        Pixel size in um; converts every length in ``params``.
    normals : (M, N, 3) array, optional
        Unit normals; a candidate whose mean tilt is below 1 degree counts as flat (bare primer)
        even if the height map shows a little relief.
    mask : (M, N) bool, optional
        True = analyse; False pixels never belong to a protrusion.
    params : DetectionParams, optional
    left_out : (M, N) bool, optional
        With normals: the pixels whose gradients ``height_um`` was integrated without
        (:func:`uvps.core.pipeline.detection_height`: a crack's walls, whose normals are wrong).
        The height departs from the normals there by construction, so the ``artefact`` rule's
        mismatch is measured over a candidate's other pixels (when they are at least half of it).
        Ignored without normals.
    progress : callable, optional
        ``progress(fraction, message)``.

    Returns
    -------
    Detection

    Notes
    -----
    Cues: the module docstring; rejections: :data:`REJECTION_RULES`. Cost: a few full-image
    filters and FFTs, one diameter opening on block maxima, ``h_maxima`` on the raised areas, one
    watershed, a robust plane and a watershed per group of footprints in its crop, the
    measurements on the candidates' crops: ~11 s of CPU at 4000 x 3000 on one core
    (``scripts/benchmark_detection_speed.py``, ``docs/benchmarks.md``).

    References
    ----------
    Salvant J. et al., "Photometric stereo by UV-induced fluorescence to detect protrusions on
    Georgia O'Keeffe's paintings", Sec. "Automated Protrusion Detection" (the two masks and
    their union). Breen E. J., Jones R., "Attribute openings, thinnings, and
    granulometries", Comput. Vis. Image Underst. 64 (1996) 377-389.

    Examples
    --------
    >>> import numpy as np
    >>> yy, xx = np.mgrid[:120, :120]
    >>> rho2 = ((yy - 60) ** 2 + (xx - 60) ** 2) / 10.0 ** 2      # a dome 20 px = 300 um wide
    >>> height = np.where(rho2 < 1, 60.0 * (1 - rho2), 0.0)
    >>> det = detect_protrusions(np.ones((120, 120)), height, pixel_size_um=15.0)
    >>> int(det.labels.max()), str(det.source[0])
    (1, 'height')
    """
    a, h, px, p = _validate(albedo, height_um, pixel_size_um, normals, mask, params, left_out)
    lum = _brightness(a if a.ndim == 2 or a.shape[2] == 3 else a[..., 0])
    measured = np.isfinite(h) & np.isfinite(lum)
    valid = measured & np.asarray(mask, bool) if mask is not None else measured
    rejected = {r: 0 for r in REJECTION_REASONS}
    none = np.zeros(h.shape, np.int32)
    if valid.sum() < 16:
        _report(progress, 1.0, "done: no valid pixels")
        return Detection(none, np.zeros(0, "<U13"), none > 0, none > 0, rejected)
    _report(progress, 0.0, "height: noise, weave, compact relief")
    surf = _surface(h, valid, px, p)
    th = _thresholds(surf, px, p)
    surf = replace(surf, relief=_beside_long(surf, valid, th, p))
    cand = _candidates(lum, valid, surf, th, px, p, progress)
    diag = _diagnostics(surf, th, cand, px)
    if cand.labels.max() == 0:
        _report(progress, 1.0, "done: no candidates")
        return Detection(none, np.zeros(0, "<U13"), cand.mask_albedo, cand.height > 0, rejected,
                         surf.noise_um, diag)
    _report(progress, 0.85, "rejection")
    unmeasured = _unmeasured(measured, normals)
    feats = _candidate_features(cand, surf, normals, th, px, p, unmeasured,
                                None if left_out is None else np.asarray(left_out, bool))
    on_long, stroke_min = _stroke_slope(feats, th, px, p)
    ripple = _ripples(feats, on_long, p)
    first = _apply_rules(feats, th, px, p, on_long, stroke_min, ripple)
    reason, lab = _bumps_on_strokes(cand, surf, feats, first, th, px, p, stroke_min, ripple, unmeasured)
    rejected.update({name: int(np.sum(reason == name)) for name in REJECTION_REASONS})
    labels, source = _finish(lab, feats, reason, h.shape)
    diag.update(candidates=int(feats.lbl.size), candidate_labels=cand.labels,
                candidate_reasons=reason, stroke_bumps=int(on_long.sum()),
                stroke_slope_min=stroke_min,
                stroke_bumps_kept=int(np.sum((first != "") & (reason == ""))),
                ripples=int(ripple.sum()))
    _report(progress, 1.0, "done")
    logger.info("detect: %d protrusions (%d candidates), rejected %s, noise %.3g um",
                int(labels.max()), feats.lbl.size, rejected, surf.noise_um)
    return Detection(labels=labels, source=source, mask_albedo=cand.mask_albedo,
                     mask_height=cand.height > 0, rejected=rejected, noise_um=surf.noise_um,
                     diagnostics=diag)


def _candidates(lum, valid, surf: Surface, th: Thresholds, px: float, p: DetectionParams,
                progress: Progress) -> Candidates:
    """The cues and their union (module docstring, steps 3-6)."""
    _report(progress, 0.3, "height cue")
    hl, markers, n_h, n_peaks = _height_cue(surf.relief, th, px, p, surf.disc)
    relief = np.zeros(0)
    if n_h:
        compact = hl
        hl, relief = _local_footprints(surf.height, hl, markers, surf.relief, valid, th, p)
        if n_h > n_peaks:
            # a shoulder keeps the footprint its curvature drew: over a plane it has no peak
            # of its own, so the footprints' re-drawing (and its merging of crests) takes it
            # into its taller neighbour; its relief is the compact relief's top within it
            sh = compact > n_peaks
            hl = np.where(sh, compact, np.where(hl > n_peaks, 0, hl))
            relief[n_peaks:] = np.maximum(_label_max(surf.relief, compact, n_h)[n_peaks:], 0)
    _report(progress, 0.5, "albedo cue")
    mask_albedo = _albedo_cue(lum, valid, px, th, p)
    long_lab, t_disc = _long_areas(surf, valid, th, hl > 0)
    _report(progress, 0.7, "union")
    lab, n_a, n_l, glow = _union(hl, n_h, mask_albedo, long_lab, max(2.0, p.albedo_grow_um / px))
    return Candidates(lab, n_h, n_a, n_l, hl, relief, mask_albedo, t_disc, glow)


def _diagnostics(surf: Surface, th: Thresholds, cand: Candidates, px: float) -> dict:
    """The thresholds, what they were measured from, the counts and the rejection table."""
    return {"relief_um": th.relief_um, "dynamic_um": th.relief_um, "slope_min": th.slope_min,
            "length_um": surf.length_px * px, "noise_um": surf.noise_um,
            "noise_smoothed_um": surf.noise_smoothed_um,
            "weave_periods_um": surf.weave.periods_um, "weave_rms_um": surf.weave.rms_um,
            "weave_slope_rms": surf.weave.slope_rms, "weave_peaks": surf.weave.n_peaks,
            "height_candidates": int(cand.n_h), "albedo_only_candidates": int(cand.n_albedo),
            "long_candidates": int(cand.n_long), "candidates": 0,
            "rejection_rules": [r._asdict() for r in REJECTION_RULES]}
