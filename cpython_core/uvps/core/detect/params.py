"""The detector's options, result and validation (:func:`uvps.core.detect.detect_protrusions`)."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, NamedTuple, Optional

import numpy as np

from ...errors import UVPSInputError, check_pixel_size


Progress = Optional[Callable[[float, str], None]]


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


def _report(progress: Progress, fraction: float, message: str) -> None:
    if progress is not None:
        progress(float(fraction), message)


def _validate(albedo, height_um, pixel_size_um, normals, mask, params, left_out=None, *, ranges):
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
    _check_params(p, ranges)
    if min(h.shape) < 8:
        raise UVPSInputError(f"`height_um` must be at least 8 x 8 pixels; got {h.shape}")
    return a, h, px, p


class Range(NamedTuple):
    """The values a :class:`DetectionParams` field may take: between ``lo`` and ``hi`` (each
    included unless ``*_open``); NaN never. ``lo``/``hi`` may name another field."""

    lo: object
    hi: object
    lo_open: bool = False
    hi_open: bool = False
    note: str = ""

    def text(self) -> str:
        """``[0, 1)``, ``(0, max_width_um)``..."""
        return (("(" if self.lo_open else "[") + f"{_num(self.lo)}, {_num(self.hi)}"
                + (")" if self.hi_open else "]"))


def _num(v) -> str:
    """A bound as the docs write it: a field's name, or the number (``inf`` for infinity)."""
    return v if isinstance(v, str) else f"{v:g}"


INF = math.inf
#: The range of each option of the cues (the rejection rules declare theirs, :mod:`.rules`;
#: :data:`uvps.core.detect.rules.PARAM_RANGES` joins the two).
CUE_RANGES = {
    "smooth_um": Range(0.0, INF, hi_open=True),
    "min_dynamic_um": Range(0.0, INF, hi_open=True),
    "dynamic_k": Range(0.0, INF, hi_open=True),
    "split_fraction": Range(0.0, 1.0, True, True),
    "weak_split_fraction": Range(0.0, 1.0, hi_open=True, note="0 (or split_fraction and above) disables"),
    "crest_fraction": Range(0.0, 1.0, hi_open=True),
    "footprint_fraction": Range(0.0, 1.0, True, True),
    "weave_factor": Range(0.0, INF, note="0 disables"),
    "weave_min_period_um": Range(0.0, "weave_max_period_um", True, True),
    "weave_max_period_um": Range("weave_min_period_um", INF, True, True),
    "albedo_contrast": Range(0.0, INF, True, True),
    "template_ncc": Range(-1.0, 1.0),
    "template_scales": Range(1, INF, hi_open=True),
    "along_stroke_k": Range(0.0, INF, hi_open=True, note="0 disables"),
    "shoulder_width_um": Range(0.0, INF, hi_open=True, note="0 disables"),
    "shoulder_k": Range(0.0, INF, hi_open=True),
    "shoulder_isotropy": Range(0.0, 1.0),
    "albedo_grow_um": Range(0.0, INF, hi_open=True),
    "curl_k": Range(0.0, INF, hi_open=True, note="0 reads the run's height as it is"),
    "beside_long_fraction": Range(0.0, 1.0, hi_open=True, note="0 disables"),
}


def _check_params(p: DetectionParams, ranges: dict) -> None:
    """Every field of ``p`` within its :class:`Range` (``ranges``: name -> Range, every field:
    :data:`uvps.core.detect.rules.PARAM_RANGES`), or a one-line :class:`UVPSInputError` naming
    it and the range."""
    for name, r in ranges.items():
        v = getattr(p, name)
        lo = getattr(p, r.lo) if isinstance(r.lo, str) else r.lo
        hi = getattr(p, r.hi) if isinstance(r.hi, str) else r.hi
        try:
            x = float(v)
        except (TypeError, ValueError):
            raise UVPSInputError(f"{name} must be a number in {r.text()}; got {v!r}") from None
        ok = (lo < x if r.lo_open else lo <= x) and (x < hi if r.hi_open else x <= hi)
        if not ok:
            note = f" ({r.note})" if r.note else ""
            raise UVPSInputError(f"{name} must be in {r.text()}{note}; got {v!r}")
