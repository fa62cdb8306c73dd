"""Albedo cue: bright components that match a disc template (module docstring of
:mod:`uvps.core.detect`, step 4)."""
from __future__ import annotations

import math

import cv2
import numpy as np
from scipy import ndimage as ndi

from ._common import MIN_SMOOTH_PX, Thresholds, _label_max
from .params import DetectionParams


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
    # the same operations as ``bg = smooth(lum0 * w) / maximum(smooth(w), 1e-6)`` with each result
    # written over an operand read for the last time, and no copy made by a cast to float32 of what
    # is float32 already: this runs beside the height's surface at the detection's peak of memory
    # (scripts/benchmark_speed.py)
    lum0 = np.where(valid, lum, 0).astype(np.float32, copy=False)
    w = valid.astype(np.float32)
    for _ in range(2):
        bg = None
        den = _smooth_large(w, sigma_px)
        bg = np.divide(_smooth_large(lum0 * w, sigma_px), np.maximum(den, 1e-6, out=den), out=den)
        del w
        w = (valid & (np.abs(lum0 - bg) <= bg * thr)).astype(np.float32)
    scale = float(np.median(lum0[valid])) if valid.any() else 1.0
    out = np.maximum(bg, 1e-6 * max(scale, 1e-30), out=bg)
    np.divide(lum0, out, out=out)
    del bg
    out -= 1
    return np.where(valid, out, 0).astype(np.float32, copy=False)


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
    lum_s = np.where(valid, lum, fill).astype(np.float32, copy=False)
    if s >= MIN_SMOOTH_PX:
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
