"""Surface, step 1: the canvas weave measured on the height's power spectrum and subtracted."""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.fft
from scipy import ndimage as ndi

from .params import DetectionParams


@dataclass
class WeaveEstimate:
    """The canvas weave as measured from the height's spectrum (see :func:`_remove_weave`)."""

    periods_um: list
    rms_um: float = 0.0
    slope_rms: float = 0.0
    n_peaks: int = 0


def _ring_median(pb: np.ndarray, sel: np.ndarray) -> np.ndarray:
    """Median of the powers ``pb`` per integer radial ring ``sel`` (the bins of the searched band;
    0 where a ring is empty), indexed by ring."""
    order = np.lexsort((pb, sel))
    rs, ps = sel[order], pb[order]
    starts = np.flatnonzero(np.r_[True, rs[1:] != rs[:-1]])
    counts = np.diff(np.r_[starts, rs.size])
    med = np.zeros(int(sel.max()) + 1)
    med[rs[starts]] = ps[starts + counts // 2]
    return med


class _LogPower:
    """``np.log(power + 1e-300)`` read bin by bin (:func:`_peak_frequency` reads five bins a peak),
    not made over the whole spectrum."""

    def __init__(self, power: np.ndarray):
        self.power = power
        self.shape = power.shape

    def __getitem__(self, index):
        return np.log(self.power[index] + 1e-300)


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


def _weave_peaks(power: np.ndarray, shape, px: float, p: DetectionParams):
    """The bins of the ``rfft2`` power spectrum of an image of ``shape`` in the searched band (periods
    ``weave_min_period_um`` to ``weave_max_period_um``) whose power exceeds ``weave_factor`` times the
    median of their integer radial ring (:func:`_ring_median`), as a bool map; None when the band
    holds no bin."""
    m, n = shape
    fr = np.hypot(np.fft.fftfreq(m)[:, None], np.fft.rfftfreq(n)[None, :])  # cycles per pixel
    band = (fr >= px / p.weave_max_period_um) & (fr <= px / p.weave_min_period_um)
    if not band.any():
        return None
    # each bin's ring, and its power over its ring's median, made in place and inside the band alone:
    # the same values as the whole-spectrum maps, without four full-size float64 / int64 temporaries
    np.multiply(fr, max(m, n), out=fr)
    ring = fr.astype(np.int64)
    del fr
    np.minimum(ring, max(m, n), out=ring)
    at = np.flatnonzero(band)
    del band
    ring_at = ring.ravel()[at]
    del ring
    med = _ring_median(power.ravel()[at], ring_at)[ring_at]
    del ring_at
    peak = np.zeros(power.shape, bool)
    above = med > 0
    peak.ravel()[at[above]] = power.ravel()[at[above]] / med[above] > p.weave_factor
    return peak


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
    # each full-size map is released once read for the last time (del): the weave runs beside the
    # noise and the albedo cue, at the run's peak of memory (scripts/benchmark_speed.py --skip run zarr
    # cal demo); the centred height is made again for the fit rather than kept through the spectrum
    mean = float(np.mean(hs))
    # the centred height times the 2-D Hann window, whose rows are made band by band (each element
    # hm[i] * hn[j], as np.outer makes it) and multiplied in place: one full-size float64 map, not three
    x = hs.astype(np.float64)
    x -= mean                   # in place: the same values, one full-size float64 map
    hm, hn = np.hanning(m), np.hanning(n)
    for r0 in range(0, m, 256):
        x[r0:r0 + 256] *= np.outer(hm[r0:r0 + 256], hn)
    spec = scipy.fft.rfft2(x)
    del x
    power = np.abs(spec)
    del spec
    np.square(power, out=power)
    peak = _weave_peaks(power, (m, n), px, p)
    if peak is None:
        return hs, none
    lab, k = ndi.label(peak, structure=np.ones((3, 3)))
    del peak
    if not k:
        return hs, none
    logp = _LogPower(power)
    # the peak bin of each component (labels are few; ndimage.maximum_position sorts them all)
    sel = np.flatnonzero(lab)
    order = np.lexsort((power.ravel()[sel], lab.ravel()[sel]))
    last = np.r_[np.flatnonzero(np.diff(lab.ravel()[sel][order])), order.size - 1]
    freqs = np.array([_peak_frequency(logp, *np.unravel_index(sel[order[i]], lab.shape))
                      for i in last])
    del power, lab, logp, sel, order
    x = hs.astype(np.float64)
    x -= mean
    coef, gram = _fit_sinusoids(x, freqs)
    del x
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
    return (hs - comp).astype(np.float32, copy=False), est


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
    out = u.real @ v.real
    out -= u.imag @ v.imag      # in place: the same values, one float64 map fewer
    return out.astype(np.float32)
