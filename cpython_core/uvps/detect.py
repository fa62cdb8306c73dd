"""Automated metal-soap protrusion detection from the fluorescence albedo and the height map.

The paper (Salvant et al., "Automated Protrusion Detection") builds mask 1 from a colour threshold
plus template matching on the albedo and mask 2 from OpenCV blob detection on the height map, and
takes their union; it under-counts and is fooled by brush-stroke ridges and bare primer. Here:

1. **Height cue** (mask 2). The low-frequency surface (canvas bow) is removed with a grey opening
   by a disc wider than the widest protrusion (white top-hat ``t``, um); the canvas weave, a few
   sharp spectral peaks, is notched out of ``t`` (FFT of its periodic component, Moisan 2011).
   Protrusions are the regional maxima of ``t`` whose *dynamic* (rise above the highest saddle
   to a higher peak; :func:`skimage.morphology.h_maxima`) exceeds
   ``max(min_dynamic_um, dynamic_k * noise, texture_k * texture)``, so noise never splits a dome
   or a ridge crest. Each marker grows by watershed on ``-t``; its footprint is where ``t``
   exceeds ``base + footprint_fraction * (peak - base)``, ``base`` being the mean of ``t`` on a
   thin ring around the basin; interior holes (caldera craters) are filled.
2. **Albedo cue** (mask 1). Brightness contrast ``c = L / L_bg - 1`` against a local background
   (normalised Gaussian average excluding bright outliers, over ~2x the widest protrusion), above
   ``albedo_contrast``; each connected component is kept when a disc template at one of a few
   scales matches it (:func:`cv2.matchTemplate`, normalised correlation >= ``template_ncc``).
3. **Union**: height footprints extended by the overlapping albedo pixels nearby; albedo components
   with no height marker become their own candidates.
4. **Rejection** (:func:`skimage.measure.regionprops_table`): ``too_small`` / ``too_large``
   (equivalent diameter outside ``[min_width_um, max_width_um]``), ``ridge`` (minor/major axis
   ratio below ``ridge_axis_ratio`` and longer than ``ridge_min_length_um``, or a low piece of
   such a long raised area: brush strokes),
   ``flat_bright`` (bright but without relief above ``max(min_dynamic_um, dynamic_k * noise)``:
   bare primer), ``weave`` (relief / width below ``min_relief_ratio``: canvas weave, the
   low parts of a ridge). A protrusion that does not fluoresce more than its surround is found
   from its height alone.

Every length option is in micrometres and converted with ``pixel_size_um``.
"""
from __future__ import annotations

import logging
import math
from dataclasses import dataclass, field
from typing import Callable, Optional

import cv2
import numpy as np
from scipy import ndimage as ndi
from skimage.measure import regionprops_table
from skimage.morphology import h_maxima
from skimage.segmentation import expand_labels, watershed

from .errors import UVPSInputError

logger = logging.getLogger(__name__)

__all__ = ["DetectionParams", "Detection", "detect_protrusions", "REJECTION_REASONS"]

REJECTION_REASONS = ("too_small", "too_large", "ridge", "flat_bright", "weave")

Progress = Optional[Callable[[float, str], None]]


@dataclass
class DetectionParams:
    """Options of :func:`detect_protrusions`. Lengths in um, heights in um, contrasts relative.

    Attributes
    ----------
    min_width_um, max_width_um : float
        Accepted equivalent-circle diameters of a protrusion.
    smooth_um : float
        Gaussian sigma applied to the height before detection (noise), in um.
    min_dynamic_um : float
        Minimum relief of a protrusion above its surround (and dynamic of its peak), um.
    dynamic_k : float
        The same, in multiples of the height noise (estimated from second differences).
    texture_k : float
        The same, in multiples of the robust spread (1.4826 MAD) of the top-hat height: the
        surface texture (canvas weave, brush marks) that no protrusion threshold should pass.
    weave_factor : float
        Spectral peaks (periods between ``weave_min_period_um`` and ``weave_max_period_um``)
        more than this many times the median power at their frequency are notched out of the
        height (canvas weave). 0 disables.
    weave_min_period_um, weave_max_period_um : float
        Period band searched for the weave.
    footprint_fraction : float
        Height footprint: pixels above ``base + fraction * (peak - base)``.
    albedo_contrast : float
        Relative brightness above the local background for the albedo mask (0.15 = 15 %).
    template_ncc : float
        Minimum normalised correlation with a disc template for an albedo component.
    template_scales : int
        Number of disc diameters, geometric between ``min_width_um`` and ``max_width_um``.
    ridge_axis_ratio : float
        Minor/major axis ratio below which an elongated region is a brush-stroke ridge.
    ridge_min_length_um : float
        ... provided its major axis is at least this long.
    ridge_relief_ratio : float
        A candidate lying on a long elongated raised area (its elevated area passes the ridge
        test and is 3x longer than the candidate is wide) is a piece of that ridge when its
        relief / width is below this (protrusions are steeper).
    min_relief_ratio : float
        Relief (peak height above the surround) / equivalent diameter below which a region is
        too low for a protrusion (canvas weave; protrusions are 0.1-0.4).
    albedo_grow_um : float
        How far (um) the albedo outline may extend a height footprint.
    """

    min_width_um: float = 30.0
    max_width_um: float = 1000.0
    smooth_um: float = 10.0
    min_dynamic_um: float = 2.0
    dynamic_k: float = 5.0
    texture_k: float = 2.0
    weave_factor: float = 50.0
    weave_min_period_um: float = 150.0
    weave_max_period_um: float = 3000.0
    footprint_fraction: float = 0.1
    albedo_contrast: float = 0.15
    template_ncc: float = 0.5
    template_scales: int = 4
    ridge_axis_ratio: float = 0.4
    ridge_min_length_um: float = 150.0
    ridge_relief_ratio: float = 0.1
    min_relief_ratio: float = 0.05
    albedo_grow_um: float = 60.0


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
        Counts of rejected candidates by reason (:data:`REJECTION_REASONS`).
    noise_um : float
        Height noise estimate (um) used for the thresholds.
    diagnostics : dict
        ``dynamic_um`` / ``relief_min_um`` (thresholds used), ``texture_um``,
        ``weave_bins_notched``, counts (``candidates``, ``height_candidates``,
        ``albedo_only_candidates``), and ``candidate_labels`` ((M, N) int32, every candidate
        before rejection) with ``candidate_reasons`` (per candidate, "" = kept), for overlays.
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


def _validate(albedo, height_um, pixel_size_um, normals, mask, params):
    h = np.asarray(height_um)
    if h.ndim != 2:
        raise UVPSInputError(f"`height_um` must be (M, N); got shape {h.shape}")
    a = np.asarray(albedo)
    if not (a.shape == h.shape or (a.ndim == 3 and a.shape[:2] == h.shape and a.shape[2] in (1, 3))):
        raise UVPSInputError(f"`albedo` must be (M, N) or (M, N, 3) with (M, N) = {h.shape}; got shape {a.shape}")
    try:
        px = float(pixel_size_um)
    except (TypeError, ValueError):
        raise UVPSInputError(f"`pixel_size_um` must be a positive number; got {pixel_size_um!r}") from None
    if not (math.isfinite(px) and px > 0):
        raise UVPSInputError(f"`pixel_size_um` must be a positive number; got {pixel_size_um!r}")
    if normals is not None and np.shape(normals) != h.shape + (3,):
        raise UVPSInputError(f"`normals` must be (M, N, 3) with (M, N) = {h.shape}; got shape {np.shape(normals)}")
    if mask is not None and np.shape(mask) != h.shape:
        raise UVPSInputError(f"`mask` must be (M, N) = {h.shape}; got shape {np.shape(mask)}")
    p = params if params is not None else DetectionParams()
    if not isinstance(p, DetectionParams):
        raise UVPSInputError(f"`params` must be a DetectionParams; got {type(p).__name__}")
    if not (0 < p.min_width_um < p.max_width_um):
        raise UVPSInputError(f"need 0 < min_width_um < max_width_um; got {p.min_width_um}, {p.max_width_um}")
    if min(h.shape) < 8:
        raise UVPSInputError(f"`height_um` must be at least 8 x 8 pixels; got {h.shape}")
    return a, h, px, p


def _opening_background(img: np.ndarray, diameter_px: float) -> np.ndarray:
    """Grey opening by a disc (the lower envelope of everything narrower than the disc).

    Large discs are applied on an area-averaged copy reduced so the disc is <= ~25 px, then
    interpolated back: the background is smooth at that scale and this keeps the cost small.
    """
    m, n = img.shape
    f = max(1, int(diameter_px // 25))
    small = cv2.resize(img, (max(n // f, 1), max(m // f, 1)), interpolation=cv2.INTER_AREA) if f > 1 else img
    d = max(3, int(round(diameter_px / f)) | 1)
    se = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (d, d))
    opened = cv2.morphologyEx(small, cv2.MORPH_OPEN, se, borderType=cv2.BORDER_REFLECT)
    if f > 1:
        opened = cv2.resize(opened, (n, m), interpolation=cv2.INTER_LINEAR)
        opened = np.minimum(opened, img)  # an opening never exceeds the image
    return opened


def _periodic_smooth(u: np.ndarray) -> tuple:
    """Moisan's periodic + smooth decomposition ``u = p + s`` (J. Math. Imaging Vis. 39, 2011).

    ``p`` has no jump across the image borders when repeated, so its FFT has no edge
    artefacts; ``s`` is smooth (it carries the border jumps). Hand-written: no library has it.
    """
    m, n = u.shape
    v = np.zeros((m, n), np.float64)
    v[0, :] = u[-1, :] - u[0, :]
    v[-1, :] = u[0, :] - u[-1, :]
    v[:, 0] += u[:, -1] - u[:, 0]
    v[:, -1] += u[:, 0] - u[:, -1]
    cy = np.cos(2 * np.pi * np.arange(m) / m)[:, None]
    cx = np.cos(2 * np.pi * np.fft.rfftfreq(n))[None, :]
    den = 2 * cy + 2 * cx - 4
    den[0, 0] = 1.0
    sv = np.fft.rfft2(v) / den
    sv[0, 0] = 0
    smooth = np.fft.irfft2(sv, s=(m, n))
    return u - smooth, smooth


def _remove_periodic(t: np.ndarray, px: float, min_period_um: float, max_period_um: float,
                     factor: float) -> tuple:
    """Remove a periodic texture (canvas weave) by notching strong spectral peaks.

    A weave is a few sharp peaks of the 2-D spectrum (and harmonics) at periods of a few hundred
    um; a protrusion's spectrum is broad and smooth, so zeroing the few bins whose power exceeds
    ``factor`` times the median power at the same spatial frequency (periods in
    ``[min_period_um, max_period_um]``) removes the weave and leaves the domes. The FFT is taken
    of the periodic component of ``t`` (:func:`_periodic_smooth`) so the edges do not ring.
    Hand-written because no library does spectral notch filtering of a 2-D image.
    Returns (filtered, number of notched coefficients).
    """
    m, n = t.shape
    per, smooth = _periodic_smooth(t.astype(np.float64))
    spec = np.fft.rfft2(per)
    fy = np.fft.fftfreq(m)[:, None]
    fx = np.fft.rfftfreq(n)[None, :]
    fr = np.hypot(fy, fx)  # cycles per pixel
    band = (fr >= px / max_period_um) & (fr <= px / min_period_um)
    if not band.any():
        return t, 0
    power = spec.real ** 2 + spec.imag ** 2
    ring = np.minimum((fr * max(m, n)).astype(np.int64), max(m, n))
    sel = ring[band]
    pb = power[band]
    # median power per radial ring: sort by (ring, power), take each ring's middle element
    order = np.lexsort((pb, sel))
    rs, ps = sel[order], pb[order]
    starts = np.flatnonzero(np.r_[True, rs[1:] != rs[:-1]])
    counts = np.diff(np.r_[starts, rs.size])
    ring_med = np.zeros(int(ring.max()) + 1)
    ring_med[rs[starts]] = ps[starts + counts // 2]
    peaks = band & (power > factor * ring_med[ring])
    if not peaks.any():
        return t, 0
    peaks = ndi.binary_dilation(peaks, structure=np.ones((3, 3))) & band
    spec[peaks] = 0
    out = np.fft.irfft2(spec, s=(m, n)) + smooth
    return out.astype(np.float32), int(peaks.sum())


def _noise_sigma(h: np.ndarray, valid: np.ndarray) -> float:
    """Robust white-noise sigma from second differences along rows and columns.

    A second difference cancels planes and slopes; for white noise its variance is 6 sigma^2.
    """
    d = np.concatenate([
        (h[:, 2:] - 2 * h[:, 1:-1] + h[:, :-2])[valid[:, 2:] & valid[:, 1:-1] & valid[:, :-2]],
        (h[2:] - 2 * h[1:-1] + h[:-2])[valid[2:] & valid[1:-1] & valid[:-2]],
    ])
    if d.size == 0:
        return 0.0
    mad = np.median(np.abs(d - np.median(d)))
    return float(1.4826 * mad / math.sqrt(6.0))


def _disc_template(d: float) -> np.ndarray:
    """A disc of diameter ``d`` px centred in a square of side ~2d (its surround is part of it)."""
    side = max(5, int(math.ceil(2 * d)) | 1)
    c = (side - 1) / 2
    yy, xx = np.mgrid[:side, :side]
    r = np.hypot(yy - c, xx - c)
    # anti-aliased edge so that small discs stay discs
    return np.clip(d / 2 - r + 0.5, 0, 1).astype(np.float32)


def _template_score(contrast: np.ndarray, diameters) -> np.ndarray:
    """Max over disc diameters of the normalised correlation (TM_CCOEFF_NORMED), centred."""
    m, n = contrast.shape
    best = np.full((m, n), -1.0, np.float32)
    src = np.ascontiguousarray(contrast, dtype=np.float32)
    for d in diameters:
        tpl = _disc_template(d)
        k = tpl.shape[0]
        half = k // 2
        if k >= min(m, n):
            continue
        padded = cv2.copyMakeBorder(src, half, half, half, half, cv2.BORDER_REFLECT)
        score = cv2.matchTemplate(padded, tpl, cv2.TM_CCOEFF_NORMED)
        np.maximum(best, score[:m, :n], out=best)
    return best


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


def _brightness(albedo: np.ndarray) -> np.ndarray:
    a = albedo.astype(np.float32, copy=False)
    return a.sum(axis=2) if a.ndim == 3 else a


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

    Two passes: the second excludes pixels already brighter than the threshold, so crowded
    protrusions do not raise their own background.
    """
    lum0 = np.where(valid, lum, 0).astype(np.float32)
    w = valid.astype(np.float32)
    bg = None
    for _ in range(2):
        bg = _smooth_large(lum0 * w, sigma_px) / np.maximum(_smooth_large(w, sigma_px), 1e-6)
        w = (valid & (lum0 <= bg * (1 + thr))).astype(np.float32)
    scale = float(np.median(lum0[valid])) if valid.any() else 1.0
    return np.where(valid, lum0 / np.maximum(bg, 1e-6 * max(scale, 1e-30)) - 1, 0).astype(np.float32)


def detect_protrusions(albedo, height_um, *, pixel_size_um, normals=None, mask=None, params=None,
                       progress: Progress = None) -> Detection:
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
        Unit normals; a region whose mean tilt is below 1 degree counts as flat (bare primer)
        even if the height map shows a little relief.
    mask : (M, N) bool, optional
        True = analyse; False pixels never belong to a protrusion.
    params : DetectionParams, optional
    progress : callable, optional
        ``progress(fraction, message)``.

    Returns
    -------
    Detection

    Notes
    -----
    See the module docstring for the method. Cost: a handful of full-image filters and FFTs,
    ``h_maxima`` on the raised areas only, one watershed; 1.5-3.5 s for 1600 x 1200 pixels on
    one (shared) core (``scripts/benchmark_protrusions.py``).

    References
    ----------
    Salvant J. et al., "Photometric stereo by UV-induced fluorescence to detect protrusions on
    Georgia O'Keeffe's paintings", Sec. "Automated Protrusion Detection" (the two masks and
    their union). Moisan L., "Periodic plus smooth image decomposition", J. Math. Imaging Vis.
    39 (2011) 161-179.
    """
    a, h, px, p = _validate(albedo, height_um, pixel_size_um, normals, mask, params)
    m, n = h.shape
    lum = _brightness(a if a.ndim == 2 or a.shape[2] == 3 else a[..., 0])
    valid = np.isfinite(h) & np.isfinite(lum)
    if mask is not None:
        valid &= np.asarray(mask, bool)
    rejected = {r: 0 for r in REJECTION_REASONS}
    empty = np.zeros((m, n), bool)
    if valid.sum() < 16:
        _report(progress, 1.0, "done: no valid pixels")
        return Detection(np.zeros((m, n), np.int32), np.zeros(0, "<U13"), empty, empty.copy(), rejected)

    min_w, max_w = p.min_width_um / px, p.max_width_um / px
    # ---- height cue -------------------------------------------------------------------------
    _report(progress, 0.0, "height cue")
    fill = float(np.median(h[valid]))
    h0 = np.where(valid, h, fill).astype(np.float32)
    noise = _noise_sigma(h0, valid)
    s = p.smooth_um / px
    hs = cv2.GaussianBlur(h0, (0, 0), s, borderType=cv2.BORDER_REFLECT) if s >= 0.3 else h0
    t = hs - _opening_background(hs, 1.2 * max_w + 2)
    t[~valid] = 0
    n_notched = 0
    if p.weave_factor > 0:
        t, n_notched = _remove_periodic(t, px, p.weave_min_period_um, p.weave_max_period_um,
                                        p.weave_factor)
        t = t - _opening_background(t, 1.2 * max_w + 2)
        t[~valid] = 0
    # white noise after the separable Gaussian: times the kernel's L2 norm, squared (2-D)
    if s >= 0.3:
        k1 = cv2.getGaussianKernel(2 * int(math.ceil(4 * s)) + 1, s)
        noise_s = noise * float(np.sum(k1 ** 2))
    else:
        noise_s = noise
    # texture level (weave, fine brush marks): robust spread of the top-hat itself
    # the opening sits on the noise minima: put the top-hat's typical level at 0
    tv = t[valid]
    t_med = float(np.median(tv))
    t -= t_med
    t[~valid] = 0
    texture = float(1.4826 * np.median(np.abs(tv - t_med)))
    dyn = max(p.min_dynamic_um, p.dynamic_k * noise_s, p.texture_k * texture)
    relief_min = dyn
    _report(progress, 0.2, "height maxima")
    low = valid & (t >= 0.5 * dyn)
    comp, ncomp = ndi.label(low, structure=np.ones((3, 3)))
    markers = np.zeros((m, n), np.int32)
    n_h = 0
    if ncomp:
        # h_maxima per elevated area (same maxima as on the whole image: every path to a higher
        # maximum through a saddle above 0.5 * dyn stays inside the area); skip areas never
        # reaching dyn. Much cheaper than the full-image reconstruction.
        top = _label_max(t, comp, ncomp)
        # an area rising less than 1.5 dyn holds one maximum of dynamic >= dyn at most: its top
        simple = np.concatenate([[False], (top >= dyn) & (top < 1.5 * dyn)])
        at_top = simple[comp] & (t >= np.concatenate([[np.inf], top])[comp])
        markers[at_top] = comp[at_top]
        n_h = ncomp
        for k_comp, sl in enumerate(ndi.find_objects(comp)):
            if top[k_comp] < 1.5 * dyn:
                continue
            inside = comp[sl] == k_comp + 1
            sub = np.where(inside, t[sl], 0.0).astype(np.float64)
            hm = h_maxima(sub, dyn) & (sub >= dyn) & inside
            lab, k = ndi.label(hm, structure=np.ones((3, 3)))
            if k:
                markers[sl][lab > 0] = lab[lab > 0] + n_h
                n_h += k
        # compact the marker ids to 1..n_h
        used = np.unique(markers[markers > 0])
        lut = np.zeros(n_h + 1, np.int32)
        lut[used] = np.arange(1, used.size + 1, dtype=np.int32)
        markers = lut[markers]
        n_h = int(used.size)
    _report(progress, 0.4, "height footprints")
    ws = watershed(-t, markers, mask=low | (markers > 0)) if n_h else np.zeros((m, n), np.int32)
    if n_h:
        peak = _label_max(t, ws, n_h)
        ring = expand_labels(ws, distance=2) * (ws == 0)
        base = _label_mean(t, ring, n_h)
        lut_cut = np.concatenate([[np.inf], base + p.footprint_fraction * (peak - base)])
        foot = (t >= lut_cut[ws]) & (ws > 0)
        hl = ws * foot
        # fill each footprint's holes (caldera crater) as a traced outline would
        filled = ndi.binary_fill_holes(hl > 0)
        holes = filled & (hl == 0)
        if holes.any():
            hl = expand_labels(hl, distance=max(m, n)) * filled  # holes take the enclosing label
            hl[~filled] = 0
        hl = hl.astype(np.int32)
    else:
        hl = np.zeros((m, n), np.int32)
        peak = base = np.zeros(0)
    mask_height = hl > 0

    # ---- albedo cue -------------------------------------------------------------------------
    _report(progress, 0.55, "albedo cue")
    lum_s = np.where(valid, lum, float(np.median(lum[valid]))).astype(np.float32)
    if s >= 0.3:
        lum_s = cv2.GaussianBlur(lum_s, (0, 0), s, borderType=cv2.BORDER_REFLECT)
    contrast = _albedo_contrast(lum_s, valid, max(2.0, 0.5 * max_w), p.albedo_contrast)
    raw = valid & (contrast > p.albedo_contrast)
    acomp, na = ndi.label(raw, structure=np.ones((3, 3)))
    mask_albedo = np.zeros((m, n), bool)
    if na:
        k = max(int(p.template_scales), 1)
        diam = np.geomspace(max(min_w, 2.0), max(max_w, min_w * 1.01, 2.5), k)
        score = _template_score(np.clip(contrast, 0, 2 * p.albedo_contrast + 0.5), diam)
        best = _label_max(score, acomp, na)
        keep = np.concatenate([[False], best >= p.template_ncc])
        mask_albedo = keep[acomp]

    # ---- union ------------------------------------------------------------------------------
    _report(progress, 0.75, "union")
    grow = max(2.0, p.albedo_grow_um / px)
    near = expand_labels(hl, distance=grow)
    lab = np.where(hl > 0, hl, np.where(mask_albedo, near, 0)).astype(np.int32)
    # albedo components not touching any height footprint become their own candidates
    acomp2, na2 = ndi.label(mask_albedo & (lab == 0), structure=np.ones((3, 3)))
    if na2:
        lab = np.where(acomp2 > 0, acomp2 + n_h, lab).astype(np.int32)
    n_all = n_h + na2
    if n_all == 0:
        _report(progress, 1.0, "done: no candidates")
        return Detection(np.zeros((m, n), np.int32), np.zeros(0, "<U13"), mask_albedo, mask_height,
                         rejected, noise, {"dynamic_um": dyn, "candidates": 0})

    # ---- measurements and rejection ---------------------------------------------------------
    _report(progress, 0.85, "rejection")
    n_lab = int(lab.max())
    area = np.bincount(lab.ravel(), minlength=n_lab + 1)[1:]
    lbl = np.flatnonzero(area) + 1
    area = area[lbl - 1]
    eqd = np.sqrt(4 * area / np.pi)
    # relief of every candidate above a ring around it (albedo-only ones included)
    ring = expand_labels(lab, distance=max(2.0, 0.25 * min_w + 1)) * (lab == 0)
    relief = (_label_max(t, lab, n_lab) - _label_mean(t, ring, n_lab))[lbl - 1]
    n_alb = np.bincount(lab[mask_albedo], minlength=n_lab + 1)[lbl]
    has_h = lbl <= n_h
    has_a = n_alb >= np.maximum(1, 0.2 * area)
    # shape (regionprops_table, one Python step per region) only where it can decide something:
    # candidates of an acceptable size with some relief or colour (skips the many noise bumps)
    major = np.zeros(lbl.size)
    minor = np.zeros(lbl.size)
    need = (eqd >= min_w) & (eqd <= max_w) & ((relief >= relief_min) | has_a)
    if need.any():
        keep_lut = np.zeros(n_lab + 1, np.int32)
        keep_lut[lbl[need]] = lbl[need]
        props = regionprops_table(keep_lut[lab], properties=("label", "axis_major_length",
                                                             "axis_minor_length"))
        pos = np.searchsorted(lbl, props["label"])
        major[pos] = props["axis_major_length"]
        minor[pos] = props["axis_minor_length"]
    # a low piece of a long elongated raised area (a brush stroke broken into bumps by its own
    # relief) is part of a ridge: judge the elevated area holding the candidate
    on_ridge = np.zeros(lbl.size, bool)
    if n_h and ncomp:
        comp_of = _label_max(comp, lab, n_lab)[lbl - 1]
        used = np.unique(comp_of[has_h & np.isfinite(comp_of)]).astype(np.int64)
        used = used[used > 0]
        if used.size:
            sub = np.zeros(ncomp + 1, np.int32)
            sub[used] = used
            cprops = regionprops_table(sub[comp], properties=("label", "axis_major_length",
                                                              "axis_minor_length"))
            c_ratio = np.ones(ncomp + 1)
            c_major = np.zeros(ncomp + 1)
            c_ratio[cprops["label"]] = cprops["axis_minor_length"] / np.maximum(cprops["axis_major_length"], 1e-9)
            c_major[cprops["label"]] = cprops["axis_major_length"]
            ci = np.where(has_h & np.isfinite(comp_of), comp_of, 0).astype(np.int64)
            on_ridge = (ci > 0) & (c_ratio[ci] < p.ridge_axis_ratio) & (c_major[ci] * px >= p.ridge_min_length_um) \
                & (c_major[ci] >= 3 * eqd)
    flat = relief < relief_min
    if normals is not None:
        nz = np.clip(np.asarray(normals, np.float64)[..., 2], -1, 1)
        tilt = np.degrees(np.arccos(np.where(np.isfinite(nz), nz, 1)))
        flat |= _label_mean(tilt, lab, n_lab)[lbl - 1] < 1.0
    reason = np.full(lbl.size, "", dtype="<U13")
    ratio = np.where(major > 0, minor / np.maximum(major, 1e-9), 1.0)
    rules = [
        ("too_small", eqd < min_w),
        ("too_large", eqd > max_w),
        ("ridge", ((ratio < p.ridge_axis_ratio) & (major * px >= p.ridge_min_length_um))
                  | (on_ridge & (relief < p.ridge_relief_ratio * eqd * px))),
        ("flat_bright", flat & has_a & ~has_h),
        ("weave", (relief < p.min_relief_ratio * eqd * px) | flat),
    ]
    for name, bad in rules:
        sel = bad & (reason == "")
        reason[sel] = name
        rejected[name] += int(sel.sum())
    ok = reason == ""
    lut = np.zeros(int(lab.max()) + 1, np.int32)
    lut[lbl[ok]] = np.arange(1, int(ok.sum()) + 1, dtype=np.int32)
    labels = lut[lab]
    source = np.where(has_h & has_a, "albedo+height", np.where(has_h, "height", "albedo"))[ok].astype("<U13")
    _report(progress, 1.0, "done")
    logger.info("detect: %d protrusions (%d candidates), rejected %s, noise %.3g um",
                int(ok.sum()), lbl.size, rejected, noise)
    return Detection(labels=labels, source=source, mask_albedo=mask_albedo, mask_height=mask_height,
                     rejected=rejected, noise_um=noise,
                     diagnostics={"dynamic_um": dyn, "relief_min_um": relief_min,
                                  "candidates": int(lbl.size), "height_candidates": int(n_h),
                                  "candidate_labels": lab, "candidate_reasons": reason,
                                  "texture_um": texture, "weave_bins_notched": n_notched,
                                  "albedo_only_candidates": int(na2)})
