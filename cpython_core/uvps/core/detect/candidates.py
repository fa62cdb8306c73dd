"""Candidates: the cues run and united into one label image, each candidate with its kind
(module docstring of :mod:`uvps.core.detect`, steps 3-7)."""
from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
from scipy import ndimage as ndi

from ._common import Thresholds, _expand_labels, _kept_components, _label_max
from .albedo import _albedo_cue
from .footprints import _local_footprints
from .height import _height_cue
from .params import DetectionParams, Progress, _report
from .surface import Surface


#: The kinds of candidate (:attr:`Candidates.kind`): a compact peak's footprint (the height cue,
#: grown into its own glow), an albedo component that no footprint took (the albedo cue alone),
#: a long raised area that the compact relief leaves out (a stroke, a crack lip).
HEIGHT, ALBEDO, LONG = "height", "albedo", "long"


def _long_areas(surf: Surface, valid, th: Thresholds, taken: np.ndarray) -> tuple:
    """Raised areas that the compact relief leaves out (strokes, crack lips).

    The disc top-hat (:func:`_disc_tophat`) keeps what is narrower than ``L``; what rises above
    the compact relief by the relief threshold but lies outside every compact footprint
    (``taken``) is a long structure. Returns (labels, disc top-hat in um).
    """
    raised = valid & (surf.disc - surf.relief >= th.relief_um) & ~taken
    lab, _ = ndi.label(raised, structure=np.ones((3, 3)))
    return lab.astype(np.int32, copy=False), surf.disc


def _union(hl: np.ndarray, n_h: int, mask_albedo: np.ndarray, long_lab: np.ndarray,
           grow_px: float) -> tuple:
    """One label image of every candidate: height footprints (1..n_h) extended by the pixels
    of their own glow within ``grow_px`` of them (an albedo component that overlaps the
    footprint: a bright area of paint beside a protrusion that does not glow is not its
    outline), then the albedo components within ``grow_px`` of none of them, then long raised
    areas touching neither. An albedo component within ``grow_px`` of a footprint that it does
    not overlap is neither an outline nor a candidate. Returns (labels, the kind of each id
    0..n: :data:`HEIGHT`, :data:`ALBEDO` or :data:`LONG`, the albedo components:
    ``mask_albedo`` labelled, 8-connected)."""
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
    del near, both, ext, ok                              # full-size maps read for the last time
    at, new, na = _kept_components(glow, ~joined)
    lab.ravel()[at] = new + n_h                          # in place: lab is ours
    taken = cv2.dilate((lab > 0).view(np.uint8), np.ones((3, 3), np.uint8),
                       borderType=cv2.BORDER_CONSTANT, borderValue=0).view(bool)
    touch = np.zeros(int(long_lab.max()) + 1, bool)
    touch[long_lab[taken]] = True
    at, new, nl = _kept_components(long_lab, ~touch)
    lab.ravel()[at] = new + (n_h + na)
    kind = np.array([""] + [HEIGHT] * n_h + [ALBEDO] * na + [LONG] * nl, dtype="<U6")
    return lab, kind, glow


@dataclass
class Candidates:
    """Every candidate of :func:`_candidates`, before rejection."""

    labels: np.ndarray          # (M, N) int32, one id per candidate
    n_h: int
    n_albedo: int
    n_long: int
    height: np.ndarray          # (M, N) int32 height footprints
    height_relief: np.ndarray   # (n_h,) relief of each height footprint over its local plane
    mask_albedo: np.ndarray     # (M, N) bool
    t_disc: np.ndarray          # (M, N) disc top-hat of the height (um)
    glow: np.ndarray            # (M, N) int32 components of mask_albedo (8-connected)
    kind: np.ndarray            # (n + 1,) per id (index 0 unused, ""): HEIGHT, ALBEDO or LONG


def _candidates(lum, valid, surf: Surface, th: Thresholds, px: float, p: DetectionParams,
                progress: Progress, *, mask_albedo: np.ndarray = None) -> Candidates:
    """The cues and their union (module docstring, steps 3-6); ``mask_albedo``: the albedo cue
    when it was run already (:func:`_albedo_cue`, as here)."""
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
        # the cue's own label images are read for the last time: released before the union's
        # (the detection's peak of memory, scripts/benchmark_speed.py)
        del compact
    del markers
    _report(progress, 0.5, "albedo cue")
    if mask_albedo is None:
        mask_albedo = _albedo_cue(lum, valid, px, th, p)
    long_lab, t_disc = _long_areas(surf, valid, th, hl > 0)
    _report(progress, 0.7, "union")
    lab, kind, glow = _union(hl, n_h, mask_albedo, long_lab, max(2.0, p.albedo_grow_um / px))
    return Candidates(lab, n_h, int(np.sum(kind == ALBEDO)), int(np.sum(kind == LONG)), hl, relief,
                      mask_albedo, t_disc, glow, kind)
