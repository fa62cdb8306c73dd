"""The detector composed: validation, surface, cues, union, features, rules, rescue, result."""
from __future__ import annotations

import logging
from dataclasses import replace

import numpy as np
from scipy import ndimage as ndi
from skimage.segmentation import expand_labels

from ..threads import concurrently
from ._common import Thresholds, _holes
from .albedo import _albedo_cue, _brightness
from .along_stroke import _bumps_on_strokes
from .candidates import Candidates, _candidates
from .features import CandidateFeatures, _candidate_features, _unmeasured
from .params import Detection, Progress, _report, _validate
from .rules import PARAM_RANGES, REJECTION_REASONS, REJECTION_RULES, _apply_rules
from .strokes import _ripples, _stroke_slope
from .surface import Surface, _beside_long, _surface, _thresholds, _widths

# the package's name, not the module's: the detector's summary line reads "uvps.core.detect: detect: ..."
# in the Log and the CLI as it did when the detector was one module
logger = logging.getLogger("uvps.core.detect")


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
    measurements on the candidates' crops: 9.9-11.2 s at 4000 x 3000 on one core
    (``scripts/benchmark_detection_speed.py``; ``docs/benchmarks.md``, "Detection on other shapes
    and surfaces"). Independent steps run side by side when two threads are allowed
    (:func:`uvps.core.threads.concurrently`: the albedo cue beside the surface, the noise beside
    the weave, the curvature beside the peaks, ...; the same outputs to the bit;
    ``docs/decisions/speed.md``, "The detection's independent steps side by side").

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
    a, h, px, p = _validate(albedo, height_um, pixel_size_um, normals, mask, params, left_out,
                            ranges=PARAM_RANGES)
    lum = _brightness(a if a.ndim == 2 or a.shape[2] == 3 else a[..., 0])
    measured = np.isfinite(h) & np.isfinite(lum)
    valid = measured & np.asarray(mask, bool) if mask is not None else measured
    rejected = {r: 0 for r in REJECTION_REASONS}
    none = np.zeros(h.shape, np.int32)
    if valid.sum() < 16:
        _report(progress, 1.0, "done: no valid pixels")
        return Detection(none, np.zeros(0, "<U13"), none > 0, none > 0, rejected)
    _report(progress, 0.0, "height: noise, weave, compact relief")
    # the albedo cue reads the albedo and the widths only: beside the height's surface
    surf, (mask_albedo, unmeasured) = concurrently(
        lambda: _surface(h, valid, px, p),
        lambda: (_albedo_cue(lum, valid, px, _widths(px, p), p), _unmeasured(measured, normals)))
    th = _thresholds(surf, px, p)
    surf = replace(surf, relief=_beside_long(surf, valid, th, p))
    cand = _candidates(lum, valid, surf, th, px, p, progress, mask_albedo=mask_albedo)
    diag = _diagnostics(surf, th, cand, px)
    if cand.labels.max() == 0:
        _report(progress, 1.0, "done: no candidates")
        return Detection(none, np.zeros(0, "<U13"), cand.mask_albedo, cand.height > 0, rejected,
                         surf.noise_um, diag)
    _report(progress, 0.85, "rejection")
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
