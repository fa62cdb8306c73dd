"""Registration of a painting's overlapping tiles: pairwise shifts, then one global solution.

A painting photographed in tiles by a moving rig (camera and lamps together, on a copy stand or an
XY stage) comes with each tile's nominal corner in the painting (the stage's positions), off by the
stage's error. As Fiji's Grid/Collection Stitching and BigStitcher do (Preibisch, Saalfeld and
Tomancak, Bioinformatics 2009, "Globally optimal stitching of tiled 3D microscopic image
acquisitions"), each pair of overlapping tiles is registered on its overlap: the few highest peaks
of the phase correlation (``skimage.feature.peak_local_max``), each with the shifts its FFT
wrap-around allows, scored by the normalised cross-correlation (NCC) of what they make overlap
(on a near-periodic paint texture the highest peak is often a copy of the pattern a few pixels
off, while the NCC is highest at the true shift), the best climbed to the NCC's maximum and refined
sub-pixel (``skimage.registration.phase_cross_correlation``, upsampled); its NCC is the pair's
confidence, and the NCC peak's curvature the directions it determines (an overlap crossed by one
straight paint edge matches all along the edge: its NCC is a ridge, and where along it the maximum
falls follows whatever else differs between the tiles). Then all pairs are reconciled by one
least-squares over the tiles' corners, each pair weighted by its confidence along the directions it
determines, dropping the pair that disagrees most with the solution while it disagrees by more than
``max_residual_px`` and the tiles stay connected. A pair left unregistered (its best NCC below
``min_confidence``) keeps its nominal relative offset, as a weak link, and its warning names why:
blank paint (no structure in the overlap), no shift within reach, or no shift that matches.

The tiles' heights are then aligned on the overlaps (:func:`align_rig_heights`): per tile an offset
and a tilt, and one error surface shared by every tile in its own frame (the rig's lamps move with the
camera); :func:`align_heights` (a free plane per tile) for tiles without their levelling record.

Frames: corners ``(x, y)`` in painting pixels (x to the right = column, y down = row: the layout's
and the tables' ``x_px``, ``y_px``); a tile's pixel ``(r, c)`` is the painting's ``(y + r, x + c)``.
The solution's frame is the nominal layout's: the mean correction over the tiles is zero.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np
from scipy import ndimage, sparse
from scipy.sparse import csgraph

from .irradiance import lamp_vectors, pixel_coordinates_mm
from .level import legendre_uv
from .tiles import overlap_box  # noqa: F401 - re-exported (the batch checks its layout with it)

log = logging.getLogger(__name__)


@dataclass
class PairShift:
    """One overlapping pair's measurement.

    ``dx, dy``: the correction of ``b``'s corner relative to ``a``'s (painting pixels): the pair
    says ``corner_b - corner_a = guess_b - guess_a + (dx, dy)``. ``confidence``: normalised
    cross-correlation of the overlap once shifted (-1..1; -1: no shift within ``search`` leaves
    enough in common). ``texture``: the overlap's structure (:func:`texture`). ``used``: kept by the
    global solution; ``residual_px``: its disagreement with the solution, measured along the directions
    the pair determines (:func:`_least_squares`); ``why``: why it was not used. ``information``: ``(xx, xy,
    yy)`` of the NCC peak's curvature in painting ``(x, y)``, scaled so its sharpest direction is 1
    (:meth:`_NccScore.information`): ``(1, 0, 1)`` a round peak, a ridge (an overlap crossed by one straight
    paint edge) near 0 along itself; None: round.
    """

    a: str
    b: str
    dx: float = 0.0
    dy: float = 0.0
    confidence: float = 0.0
    overlap_px: int = 0
    used: bool = False
    residual_px: Optional[float] = None
    why: str = ""
    dropped: bool = False
    texture: float = 1.0
    search: str = ""
    information: Optional[tuple] = None

    @property
    def fallback(self) -> bool:
        """Not registered (nothing to register): its nominal relative offset is a weak link."""
        return not self.used and not self.dropped

    @property
    def name(self) -> str:
        return f"{self.a}-{self.b}"


@dataclass
class Registration:
    """Refined corners ``{tile: (x, y)}`` and the pairs that gave them."""

    corners: dict
    pairs: list
    warnings: list = field(default_factory=list)

    @property
    def max_residual_px(self) -> float:
        r = [p.residual_px for p in self.pairs if p.used and p.residual_px is not None]
        return float(max(r)) if r else 0.0


class ArrayTile:
    """A tile's image held in memory, (M, N) or (M, N, C): what :func:`register_tiles` reads windows
    of. A tile on disk provides the same two members (``shape``, ``window``) and is read window by
    window, so registering a painting never holds more than two overlaps."""

    def __init__(self, a):
        self.a = np.asarray(a)
        self.shape = self.a.shape[:2]

    def window(self, r0: int, r1: int, c0: int, c1: int) -> np.ndarray:
        """Grey (mean of the channels) float64 of rows r0:r1, columns c0:c1."""
        w = np.asarray(self.a[r0:r1, c0:c1], np.float64)
        return w.mean(axis=2) if w.ndim == 3 else w


def _tile(img):
    return img if hasattr(img, "window") else ArrayTile(img)


def _high_pass(g: np.ndarray, sigma: float) -> np.ndarray:
    """High-passed window (a tile's flat-field residue and exposure are not the painting's)."""
    g = np.nan_to_num(g)
    return g - ndimage.gaussian_filter(g, sigma)


def _ncc(a: np.ndarray, b: np.ndarray) -> float:
    a, b = a - a.mean(), b - b.mean()
    d = np.sqrt((a * a).sum() * (b * b).sum())
    return float((a * b).sum() / d) if d > 0 else 0.0


def _common(wa, wb, sy: int, sx: int):
    """The parts of ``wa`` and ``wb`` that a shift of ``b`` by ``(sy, sx)`` makes coincide
    (``wb[u - s]`` against ``wa[u]``)."""
    H, W = wa.shape
    ya, yb = max(0, sy), max(0, -sy)
    xa, xb = max(0, sx), max(0, -sx)
    h, w = H - abs(sy), W - abs(sx)
    if h <= 0 or w <= 0:
        return None, None
    return wa[ya:ya + h, xa:xa + w], wb[yb:yb + h, xb:xb + w]


#: Phase-correlation peaks whose shifts are scored (Preibisch et al. 2009 check the few highest, 5 by default).
N_PEAKS = 5

#: Of those, the best few (by the NCC around them) climbed to their NCC's local maxima.
N_CLIMB = 3

#: The least weight a pair's shift has along its weakest direction, relative to its sharpest (a pair whose
#: NCC is a ridge says almost nothing along it; the floor keeps its normal matrix invertible).
MIN_INFORMATION = 1e-3

#: Below this correlation of a window with itself one pixel over, the overlap holds no structure (noise only):
#: white noise decorrelates in one pixel, paint texture imaged at ~15 um per pixel does not.
MIN_TEXTURE = 0.2


def texture(win: np.ndarray) -> float:
    """How much the (high-passed) window holds to register: its correlation with itself one pixel
    over, the smaller of the two axes (about 0 for noise alone, near 1 for texture)."""
    if min(win.shape) < 2:
        return 0.0
    return min(_ncc(win[1:], win[:-1]), _ncc(win[:, 1:], win[:, :-1]))


def _peaks(win_a, win_b, max_shift_px: float, n_peaks: int) -> list:
    """The ``n_peaks`` highest local maxima of the phase-correlation surface (indices modulo the
    window) among those whose shift, or a wrap-around of it, lies within ``max_shift_px``."""
    from skimage.feature import peak_local_max   # lazily: skimage's import is slow
    from scipy import fft

    prod = fft.fft2(win_a) * np.conj(fft.fft2(win_b))
    surface = fft.ifft2(prod / np.maximum(np.abs(prod), np.finfo(float).tiny)).real
    H, W = surface.shape
    m = max_shift_px + 1
    iy, ix = np.arange(H), np.arange(W)
    ok = ((iy <= m) | (H - iy <= m))[:, None] & ((ix <= m) | (W - ix <= m))[None, :]
    surface = np.where(ok, surface, surface.min())
    return [tuple(q) for q in peak_local_max(surface, min_distance=1, num_peaks=n_peaks, exclude_border=False)
            if ok[q[0], q[1]]]


@dataclass
class PairFit:
    """What :func:`pair_shift` measures between two windows: the shift ``(dy, dx)``, its confidence (the
    best NCC; -1: no shift within reach leaves enough in common), the common part's size in pixels, and
    ``information``: the NCC peak's curvature ``((yy, yx), (xy, xx))`` in window ``(row, column)``,
    scaled so its sharpest direction is 1 (None when it cannot be measured: taken as round)."""

    dy: float
    dx: float
    confidence: float
    common_px: int
    information: Optional[np.ndarray] = None


def pair_shift(win_a: np.ndarray, win_b: np.ndarray, *, max_shift_px: float, upsample: int = 20,
               min_common_px: int = 400, n_peaks: int = N_PEAKS) -> PairFit:
    """Shift ``(dy, dx)`` of the painting between two windows of one nominal overlap, its confidence,
    common size and the NCC peak's curvature (a :class:`PairFit`).

    ``win_a`` and ``win_b`` show the same nominal region of the painting from tiles a and b; the
    result is ``e_b - e_a`` (b's corner error minus a's), so that ``win_b[u - s] = win_a[u]``.
    As Fiji's stitching does (Preibisch, Saalfeld and Tomancak 2009): the ``n_peaks`` highest
    peaks of the phase correlation, each with the shifts its wrap-around allows within
    ``max_shift_px`` (and the zero shift, the guess itself), are scored by the normalised
    cross-correlation (NCC) of what they make coincide (at least ``min_common_px`` pixels); the
    best climbs to the NCC's local maximum over whole pixels, then is refined sub-pixel. On a
    near-periodic texture the highest phase peak can be a copy of the pattern a few pixels off,
    while the NCC is highest at the true shift. The NCC peak's curvature (:meth:`_NccScore.information`)
    says which directions the overlap determines: one straight paint edge across it determines the shift
    across the edge only, and along it the NCC's maximum follows whatever else differs between the tiles.
    """
    H, W = win_a.shape
    score = _NccScore(win_a, win_b, max_shift_px, min_common_px)
    cands = {(0, 0)}
    for py, px in _peaks(win_a, win_b, max_shift_px, n_peaks):
        cands.update((sy, sx) for sy in (py, py - H) for sx in (px, px - W))
    # a peak's whole-pixel shift can sit a pixel or two off the NCC's maximum: each scored by its 3 x 3
    # best, the N_CLIMB best climbed to their NCC's maxima, the highest kept
    near = sorted({score.best_near(c) for c in cands}, key=score, reverse=True)[:N_CLIMB]
    best = max((score.climb(c) for c in near), key=score)
    if score(best) <= -1.0:
        return PairFit(0.0, 0.0, -1.0, 0)
    fy, fx = score.subpixel(best, upsample)
    return PairFit(best[0] + fy, best[1] + fx, score(best), score.size(best), score.information(best))


class _NccScore:
    """The NCC of the windows' common part at an integer shift, cached; -1 outside the search.

    Hand-written: skimage's ``match_template`` scores a template wholly inside the image, whereas
    here both windows are cut to what each shift makes coincide (a common part that shrinks with
    the shift), the score Fiji's stitching gives its candidates."""

    def __init__(self, wa, wb, max_shift_px, min_common_px):
        self.wa, self.wb, self.m, self.min_px = wa, wb, max_shift_px + 1, min_common_px
        self.cache = {}

    def size(self, s) -> int:
        ca, _ = _common(self.wa, self.wb, *s)
        return 0 if ca is None else int(ca.size)

    def __call__(self, s) -> float:
        if s not in self.cache:
            ca, cb = _common(self.wa, self.wb, *s)
            inside = abs(s[0]) <= self.m and abs(s[1]) <= self.m
            ok = inside and ca is not None and ca.size >= self.min_px
            self.cache[s] = _ncc(ca, cb) if ok else -1.0
        return self.cache[s]

    def best_near(self, s) -> tuple:
        """The best-scoring of ``s`` and its 8 neighbours."""
        return max(((int(s[0]) + dy, int(s[1]) + dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)), key=self)

    def information(self, s) -> Optional[np.ndarray]:
        """The NCC's curvature at its maximum ``s``: minus the Hessian of a quadratic fitted to the 3 x 3
        shifts around it (least squares), ``((yy, yx), (xy, xx))``, scaled so its largest eigenvalue is 1,
        eigenvalues floored at ``MIN_INFORMATION``. A round peak gives the identity; a ridge (the NCC
        of an overlap crossed by one straight edge, high all along the edge) a small eigenvalue along it.
        None when a neighbour is outside the search or the peak is not curved downwards."""
        d = np.array([(dy, dx) for dy in (-1, 0, 1) for dx in (-1, 0, 1)], float)
        f = np.array([self((int(s[0]) + int(dy), int(s[1]) + int(dx))) for dy, dx in d])
        if np.any(f <= -1.0):
            return None
        design = np.column_stack([np.ones(9), d, 0.5 * d[:, 0] ** 2, d[:, 0] * d[:, 1], 0.5 * d[:, 1] ** 2])
        c = np.linalg.lstsq(design, f, rcond=None)[0]
        lam, vec = np.linalg.eigh(-np.array([[c[3], c[4]], [c[4], c[5]]]))
        if lam[-1] <= 0:
            return None
        lam = np.maximum(lam / lam[-1], MIN_INFORMATION)
        return (vec * lam) @ vec.T

    def climb(self, s, steps: int = 20) -> tuple:
        """Uphill over the 8 neighbours to the NCC's local maximum."""
        for _ in range(steps):
            nb = self.best_near(s)
            if nb == s:
                break
            s = nb
        return s

    def subpixel(self, s, upsample: int) -> tuple:
        """The fraction of a pixel: the upsampled cross-correlation of the common parts, which ``s``
        has aligned within a pixel (not phase-normalised: that whitening, which sharpens the peak for
        finding it, amplifies the noise once it is found); a parabola through the NCC if that lands
        more than a pixel off."""
        from skimage.registration import phase_cross_correlation   # lazily: skimage's import is slow

        ca, cb = _common(self.wa, self.wb, *s)
        f, _, _ = phase_cross_correlation(ca, cb, upsample_factor=upsample, normalization=None)
        if np.all(np.abs(f) <= 1.0):
            return float(f[0]), float(f[1])
        out = []
        for k in range(2):
            e = np.eye(2, dtype=int)[k]
            lo, c, hi = self(tuple(np.subtract(s, e))), self(s), self(tuple(np.add(s, e)))
            d = lo - 2 * c + hi
            out.append(float(np.clip(0.5 * (lo - hi) / d, -0.5, 0.5)) if d < 0 and lo > -1 and hi > -1 else 0.0)
        return tuple(out)


def register_tiles(images: dict, guess: dict, *, max_shift_px: float = 60.0, min_confidence: float = 0.3,
                   max_residual_px: float = 2.0, passes: int = 2, sigma: float = 8.0,
                   map_pairs: Optional[Callable] = None) -> Registration:
    """Refine the tiles' corners from their overlaps.

    Parameters
    ----------
    images : dict
        ``{tile: (M, N) or (M, N, C) array}``, or objects with ``shape`` and ``window(r0, r1,
        c0, c1)`` (grey, read from disk): what to register on (the tiles' albedo).
    guess : dict
        ``{tile: (x, y)}`` nominal corners in painting pixels (the stage's).
    max_shift_px : float
        Largest correction of one tile relative to a neighbour (twice the stage's error).
    min_confidence : float
        Pairs whose best normalised cross-correlation is lower are not registered: their
        nominal relative offset is kept as a weak link, and a warning names them and why (blank
        paint, no shift within reach, or no shift that matches).
    max_residual_px : float
        A pair whose shift disagrees with the global solution by more is dropped (worst first,
        as long as every tile stays linked) and named in a warning.
    passes : int
        Measure, solve, then measure again on the overlaps of the solution (the second pass sees
        the whole common area, not what the stage's error left of the nominal overlap).
    sigma : float
        The high-pass of the overlaps (px).
    map_pairs : callable, optional
        ``map_pairs(measure_pair, jobs) -> [measure_pair(job) for job in jobs]``, in order: where a
        pass's pairs are measured (each :class:`PairJob` reads its own two windows), for example as
        tasks of a Dask cluster (:func:`uvps.painting.stitch_painting`); default: in this process, one
        after the other. The global solution is computed here either way, and gives the same corners.

    Returns
    -------
    Registration
        Corners in the nominal layout's frame (mean correction zero), every pair with its shift,
        confidence and residual.
    """
    names = list(images)
    tiles = {n: _tile(images[n]) for n in names}
    shapes = {n: tuple(tiles[n].shape[:2]) for n in names}
    nominal = {n: (float(guess[n][0]), float(guess[n][1])) for n in names}
    current = dict(nominal)
    pairs = []
    for k in range(max(1, passes)):
        search = (max_shift_px, "the nominal offset") if k == 0 else (4.0, "the first pass's solution")
        pairs = _measure(tiles, shapes, nominal if k == 0 else current, search, sigma, map_pairs)
        current, pairs = _solve(names, nominal, pairs, min_confidence, max_residual_px)
    warnings = []
    for p in pairs:
        if not p.used:
            warnings.append(f"mosaic: pair {p.name}: {p.why}")
    return Registration(current, pairs, warnings)


@dataclass
class PairJob:
    """One overlapping pair to measure (:func:`measure_pair`): small, so it can travel to a cluster's
    worker: the two tiles as window readers (``shape`` and ``window``: on disk, a path; an in-memory
    :class:`ArrayTile` travels whole), their rounded corners ``ra``, ``rb`` and their overlap ``box``
    ``(x_lo, y_lo, x_hi, y_hi)`` in painting pixels, the search ``(max_shift_px, around what)`` and the
    high-pass ``sigma``."""

    a: str
    b: str
    tile_a: object
    tile_b: object
    ra: tuple
    rb: tuple
    box: tuple
    search: tuple
    sigma: float


def measure_pair(job: PairJob) -> PairShift:
    """The pair's shift on its overlap (:func:`pair_shift` on the two tiles' high-passed overlap windows,
    read from the tiles alone): its :class:`PairShift`, not yet solved (``used`` False)."""
    x_lo, y_lo, x_hi, y_hi = job.box
    ra, rb = job.ra, job.rb
    wa = _high_pass(job.tile_a.window(y_lo - ra[1], y_hi - ra[1], x_lo - ra[0], x_hi - ra[0]), job.sigma)
    wb = _high_pass(job.tile_b.window(y_lo - rb[1], y_hi - rb[1], x_lo - rb[0], x_hi - rb[0]), job.sigma)
    max_shift = job.search[0]
    p = PairShift(job.a, job.b, overlap_px=int(wa.size), texture=min(texture(wa), texture(wb)),
                  search=f"+-{max_shift:g} px of {job.search[1]}")
    if min(wa.shape) < 8:
        p.why = f"overlap of {wa.shape[1]} x {wa.shape[0]} px is too small to register; nominal offset kept"
        return p
    fit = pair_shift(wa, wb, max_shift_px=max_shift)
    # the windows show the painting at (corner - rounded corner) past the box, so
    # corner_b - corner_a = rounded_b - rounded_a + (sx, sy)
    p.dx, p.dy = fit.dx + rb[0] - ra[0], fit.dy + rb[1] - ra[1]
    p.confidence = fit.confidence
    if fit.information is not None:       # (row, column) -> painting (x, y)
        i = fit.information
        p.information = (float(i[1, 1]), float(i[0, 1]), float(i[0, 0]))
    return p


def pair_jobs(tiles: dict, shapes: dict, corners: dict, search: tuple, sigma: float) -> list:
    """A :class:`PairJob` for every pair of tiles that overlap at their corners (rounded), in the tiles' order."""
    names = list(tiles)
    out = []
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            ra = (round(corners[a][0]), round(corners[a][1]))
            rb = (round(corners[b][0]), round(corners[b][1]))
            box = overlap_box(ra, shapes[a], rb, shapes[b])
            if box is not None:
                out.append(PairJob(a, b, tiles[a], tiles[b], ra, rb, box, search, sigma))
    return out


def _measure(tiles, shapes, corners, search, sigma, map_pairs=None) -> list:
    """Every overlapping pair's shift within ``search = (max_shift_px, around what)``: in this process,
    one pair after the other, or through ``map_pairs(measure_pair, jobs)`` (for example on a cluster)."""
    jobs = pair_jobs(tiles, shapes, corners, search, sigma)
    if map_pairs is None:
        return [measure_pair(j) for j in jobs]
    return list(map_pairs(measure_pair, jobs))


def _why_unregistered(p: PairShift, min_confidence: float) -> str:
    """Why a measured pair is not used: blank paint only when its overlap holds no structure."""
    if p.texture < MIN_TEXTURE:
        return (f"nothing to register in the overlap (blank paint: texture {p.texture:.2f} < {MIN_TEXTURE:g}); "
                "nominal offset kept")
    if p.confidence <= -1.0:
        return (f"no shift within {p.search} leaves enough of the overlap in common; "
                "nominal offset kept")
    return (f"no shift matches (best correlation {p.confidence:.2f} < {min_confidence:g}); "
            "nominal offset kept")


def _connected(names, links) -> bool:
    """Whether the ``links`` (pairs of tile names) join every tile into one piece."""
    idx = {n: i for i, n in enumerate(names)}
    a = np.array([idx[p] for p, _ in links], int)
    b = np.array([idx[q] for _, q in links], int)
    graph = sparse.coo_matrix((np.ones(len(a)), (a, b)), shape=(len(names), len(names)))
    return csgraph.connected_components(graph, directed=False)[0] == 1


def _solve(names, nominal, pairs, min_confidence, max_residual_px):
    """Weighted least squares of the corners from the pairs' offsets (``p.dx, p.dy`` hold the
    measured ``corner_b - corner_a``), each pair weighted by its confidence along the directions its
    overlap determines (``p.information``); gauge: mean correction from ``nominal`` zero."""
    idx = {n: i for i, n in enumerate(names)}
    q = np.array([nominal[k] for k in names])
    for p in pairs:
        p.dropped = False
        p.used = p.confidence >= min_confidence and not p.why
        if not p.used and not p.why:
            p.why = _why_unregistered(p, min_confidence)
    while True:
        links = [p for p in pairs if not p.dropped]
        xy, res = _least_squares(idx, q, links)
        worst, worst_r = None, max_residual_px
        for p, r in zip(links, res):
            p.residual_px = float(r) if p.used else None
            if p.used and r > worst_r:
                if _connected(names, [(o.a, o.b) for o in links if o is not p]):
                    worst, worst_r = p, r
        if worst is None:
            break
        worst.used, worst.dropped, worst.residual_px = False, True, float(worst_r)
        worst.why = (f"its shift ({worst.dx:.1f}, {worst.dy:.1f}) px disagrees with the global solution by "
                     f"{worst_r:.1f} px; dropped")
        log.info("mosaic: pair %s dropped (%.1f px)", worst.name, worst_r)
    corners = {k: (float(xy[idx[k], 0]), float(xy[idx[k], 1])) for k in names}
    return corners, pairs


def _information(p: PairShift) -> np.ndarray:
    """The pair's 2 x 2 weight shape in painting ``(x, y)`` (identity when round or unknown)."""
    if p.information is None:
        return np.eye(2)
    xx, xy, yy = p.information
    return np.array([[xx, xy], [xy, yy]])


def _least_squares(idx: dict, q: np.ndarray, links: list) -> tuple:
    """Corners ``(n, 2)`` minimising the sum over the links of ``w r' I r`` (``r``: the link's misfit,
    ``I``: its information, ``w``: its confidence; a link not used holds the nominal offset with weight
    1e-3), and each link's residual in pixels along the direction it determines best,
    ``sqrt(r' I r)`` (the plain distance for a round peak)."""
    n = len(q)
    rows, rhs, misfit = [], [], []
    for p in links:
        a = np.zeros((2, 2 * n))                  # unknowns x_0 .. x_n-1, y_0 .. y_n-1
        for k in range(2):
            a[k, k * n + idx[p.b]], a[k, k * n + idx[p.a]] = 1.0, -1.0
        if p.used:
            b, w, info = np.array([p.dx, p.dy]), max(p.confidence, 0.05), _information(p)
        else:                                     # the stage's relative offset, weakly
            b, w, info = q[idx[p.b]] - q[idx[p.a]], 1e-3, np.eye(2)
        lam, vec = np.linalg.eigh(w * info)
        root = (vec * np.sqrt(np.maximum(lam, 0.0))) @ vec.T
        rows.append(root @ a)
        rhs.append(root @ b)
        misfit.append((a, b, info))
    gauge = np.zeros((2, 2 * n))
    gauge[0, :n] = gauge[1, n:] = 1.0 / n
    rows.append(gauge)
    rhs.append(q.mean(axis=0))
    sol = np.linalg.lstsq(np.vstack(rows), np.concatenate(rhs), rcond=None)[0]
    res = []
    for a, b, info in misfit:
        r = a @ sol - b
        res.append(float(np.sqrt(max(r @ info @ r, 0.0))))
    return np.column_stack([sol[:n], sol[n:]]), res


#: Scale of the planes' coordinates: x, y in thousands of painting pixels (a well-conditioned system).
PLANE_SCALE_PX = 1000.0


def _bilinear(img, rows, cols) -> np.ndarray:
    return ndimage.map_coordinates(np.asarray(img, np.float64), [rows, cols], order=1, mode="nearest")


def align_heights(heights: dict, corners: dict, pairs, *, step: int = 4, margin: int = 8) -> dict:
    """Per-tile offset and plane that make the tiles' heights agree on their overlaps.

    A tile's height from its own normals is known up to a constant and a low-order form (its
    integration's plane): with ``h_t`` tile ``t``'s height at painting pixel ``(X, Y)``, one
    least squares over every used pair's overlap (sampled every ``step`` pixels, ``margin`` pixels
    in from both tiles' edges, where integration errs most) finds ``(a_t, b_t, c_t)`` such that
    ``h_t + a_t + b_t x + c_t y`` (``x, y`` = painting pixels / :data:`PLANE_SCALE_PX`) agree; then
    the painting-wide plane of the aligned surface is removed (levelled as one surface).

    ``heights``: ``{tile: (M, N) array}`` (a memory map is read only on its overlaps);
    ``corners``: the registered corners; ``pairs``: the registration's :class:`PairShift` list.
    Returns ``{tile: (a, b, c)}``.
    """
    names = list(heights)
    idx = {n: i for i, n in enumerate(names)}
    n = len(names)
    # the normal equations, pair by pair: a pair's rows touch its two tiles' 3 columns alone, so each adds
    # four 3 x 3 blocks (the dense rows, samples x 3n, were 170 MB a pair for 100 tiles of 4000 x 3000)
    AtA = np.zeros((3 * n, 3 * n))
    Atb = np.zeros(3 * n)
    for p in pairs:
        if not p.used:
            continue
        ha, hb = heights[p.a], heights[p.b]
        (xa, ya), (xb, yb) = corners[p.a], corners[p.b]
        box = overlap_box((xa, ya), ha.shape, (xb, yb), hb.shape)
        if box is None:
            continue
        x_lo, y_lo, x_hi, y_hi = box
        X, Y = np.meshgrid(np.arange(np.ceil(x_lo) + margin, x_hi - margin, step),
                           np.arange(np.ceil(y_lo) + margin, y_hi - margin, step))
        X, Y = X.ravel(), Y.ravel()
        if X.size < 3:
            continue
        va, vb = _bilinear(ha, Y - ya, X - xa), _bilinear(hb, Y - yb, X - xb)
        ok = np.isfinite(va) & np.isfinite(vb)
        X, Y, va, vb = X[ok], Y[ok], va[ok], vb[ok]
        basis = np.column_stack([np.ones(X.size), X / PLANE_SCALE_PX, Y / PLANE_SCALE_PX])
        BtB, Btr = basis.T @ basis, basis.T @ (vb - va)
        a, b = slice(3 * idx[p.a], 3 * idx[p.a] + 3), slice(3 * idx[p.b], 3 * idx[p.b] + 3)
        AtA[a, a] += BtB
        AtA[b, b] += BtB
        AtA[a, b] -= BtB
        AtA[b, a] -= BtB
        Atb[a] += Btr
        Atb[b] -= Btr
    gauge = np.zeros((3, 3 * n))
    for k in range(3):
        gauge[k, k::3] = 1.0
    AtA += 1e6 * gauge.T @ gauge          # the gauge's rows (weight 1e3, right-hand side 0)
    sol, *_ = np.linalg.lstsq(AtA, Atb, rcond=None)
    coef = {k: sol[3 * idx[k]:3 * idx[k] + 3].copy() for k in names}
    # level the aligned surface as one: the plane of every tile's samples (inner grid), removed
    pts, vals = [], []
    for k in names:
        h = heights[k]
        M, N = h.shape
        rr, cc = np.meshgrid(np.arange(margin, M - margin, 4 * step), np.arange(margin, N - margin, 4 * step),
                             indexing="ij")
        X, Y = cc.ravel() + corners[k][0], rr.ravel() + corners[k][1]
        v = np.asarray(h[rr.ravel(), cc.ravel()], np.float64)
        v = v + coef[k][0] + coef[k][1] * X / PLANE_SCALE_PX + coef[k][2] * Y / PLANE_SCALE_PX
        ok = np.isfinite(v)
        pts.append(np.column_stack([np.ones(ok.sum()), X[ok] / PLANE_SCALE_PX, Y[ok] / PLANE_SCALE_PX]))
        vals.append(v[ok])
    plane, *_ = np.linalg.lstsq(np.vstack(pts), np.concatenate(vals), rcond=None)
    return {k: tuple(float(v) for v in coef[k] - plane) for k in names}


#: Total degree of the error surface every tile shares in its own frame (:func:`align_rig_heights`): a
#: quadratic (a rig's lamps' beams, off their light file, bend every tile's height alike).
SHARED_DEGREE = 2

#: The weight of each tile's measured tilt in :func:`align_rig_heights`, as a fraction of a tile's share of
#: the overlap samples: small, so the overlaps set every relative tilt they measure and the tilts the
#: normals measured set only what the overlaps cannot (the painting's curvature against the tiles' shared
#: error). Chosen on the generator (``scripts/benchmark_painting.py --beam 30 3 --bow 60``; docs/decisions/painting.md).
TILT_WEIGHT = 1e-3

#: The shared surface is kept only where it stands out of the tilts' noise: its chi-square above this
#: quantile (of F, :func:`_shrunk_shared`; the generator's painting without lamp bias: chi-square 4.7 on 3
#: terms against 25 for its 6 tiles, with the rig's beams 45 and 1420).
SHARED_SIGNIFICANCE = 0.99


@dataclass
class RigAlignment:
    """What :func:`align_rig_heights` found: each tile's height in the painting is
    ``depth + legval2d(u, v, forms[t]) + a + b x + c y`` (``planes[t] = (a, b, c)``, ``x, y`` painting
    pixels / :data:`PLANE_SCALE_PX`; ``u, v`` the tile's Legendre variables, :mod:`uvps.core.level`).

    ``forms[t]``: what levelling removed from tile ``t`` (restored) minus the ``shared`` surface (the
    tiles' common error, Legendre coefficients in a tile's frame, um); ``offsets``: each tile's constant
    before the painting-wide plane was removed; ``rms_um``: the overlaps' disagreement once aligned."""

    planes: dict
    forms: dict
    shared: np.ndarray
    offsets: dict
    rms_um: float = float("nan")


def _shared_terms(degree: int) -> list:
    """The Legendre terms ``(i, j)`` of the shared surface: total degree 2 to ``degree`` (a constant and a
    plane common to every tile make a painting-wide plane, which the overlaps cannot see)."""
    return [(i, d - i) for d in range(2, degree + 1) for i in range(d + 1)]


def _shared_basis(rows, cols, shape, degree: int) -> np.ndarray:
    """The shared surface's terms at a tile's pixels: (samples, terms)."""
    from numpy.polynomial import legendre

    u, v = legendre_uv(rows, cols, shape)
    full = legendre.legvander2d(u, v, [degree, degree])
    return full[:, [i * (degree + 1) + j for i, j in _shared_terms(degree)]]


def _raw_at(height, level, rows, cols) -> np.ndarray:
    """A tile's height as integrated (``depth`` + what levelling removed) at its pixels ``(rows, cols)``."""
    from numpy.polynomial import legendre

    v = _bilinear(height, rows, cols)
    u_, v_ = legendre_uv(rows, cols, height.shape)
    return v + legendre.legval2d(u_, v_, level)


def _overlap_samples(ha, hb, ca, cb, step, margin):
    """Painting pixels ``(X, Y)`` sampled every ``step`` px over two tiles' overlap, ``margin`` px in
    from both tiles' edges; None when too few."""
    box = overlap_box(ca, ha.shape, cb, hb.shape)
    if box is None:
        return None
    x_lo, y_lo, x_hi, y_hi = box
    X, Y = np.meshgrid(np.arange(np.ceil(x_lo) + margin, x_hi - margin, step),
                       np.arange(np.ceil(y_lo) + margin, y_hi - margin, step))
    return (X.ravel(), Y.ravel()) if X.size >= 3 else None


#: Points a side of the grid over a tile on which :func:`intensity_tilts` solves a flat canvas's normal (the
#: lamps' directions change across the field; the held-out painting's 1200 x 900 px tiles under lamps at
#: 280-420 mm: 5 x 5 and 25 x 25 points give the same tilts within 0.002 um, seeds 8-10).
INTENSITY_TILT_GRID = 5
#: Lamp positions (mm) of two tiles that agree within this are the same rig's (a light file's, read alike).
RIG_POSITION_TOL_MM = 1e-3


def intensity_tilts(positions_mm: dict, intensities: dict, shape, pixel_size_um: float) -> Optional[dict]:
    """The tilt each tile's normals took from its own lamp intensities, against the rig's.

    With the lamps' positions given (the rig's light file) and their intensities measured in each tile
    (:func:`uvps.core.lights.refine_intensities`), a tile's intensities take up part of the tile's tilt: a flat
    canvas tilted by ``t`` shades lamp ``k`` by about ``1 + t . l_xy / l_z``, which the lamp's intensity explains
    as well as the tilt does; only the texture's normals tell them apart (on the held-out painting, 1 um of
    canvas texture, the tiles measured 60-83 % of their tilt). Under a rig the lamps are the same in every
    tile, so are their intensities up to the tile's exposure: a tile's intensities against the tiles' geometric
    mean are the tile's error, and the tilt it gives is that of a flat canvas facing the camera rendered with
    the mean's intensities and solved with the tile's (least squares, as :func:`uvps.core.stereo.solve_normals`),
    averaged over a grid of the field. An error of the mean itself tilts every tile alike: a painting-wide plane.

    Parameters
    ----------
    positions_mm, intensities : dict
        ``{tile: (K, 3)}`` lamp positions (mm, the tile's frame) and ``{tile: (K,)}`` intensities, as each
        tile's ``lights.json`` holds them.
    shape : (int, int)
        The tiles' (rows, columns).
    pixel_size_um : float

    Returns
    -------
    dict or None
        ``{tile: (du, dv)}``: the Legendre coefficients (um; ``u``, ``v`` of :mod:`uvps.core.level`) of the plane
        the tile's height took from its intensities, to subtract from it; None when the tiles' lamps are not one
        rig's (a tile without positions, another number of lamps, positions that differ), a tile's intensities
        are not one per lamp, there are fewer than 3 lamps or an intensity is not a positive number.
    """
    names = list(positions_mm)
    P = [None if positions_mm[k] is None else np.asarray(positions_mm[k], float) for k in names]
    if len(names) < 2 or any(p is None or p.shape != P[0].shape or not np.allclose(p, P[0], rtol=0,
                                                                                   atol=RIG_POSITION_TOL_MM)
                             for p in P):
        return None
    # checked tile by tile: a list of another length would make a ragged array (numpy raises)
    E = [np.asarray(np.nan if intensities.get(k) is None else intensities[k], float) for k in names]
    if len(P[0]) < 3 or any(e.shape != (len(P[0]),) for e in E):   # fewer than 3 lamps: no normal
        return None
    E = np.array(E)
    if not np.all(np.isfinite(E) & (E > 0)):
        return None
    logE = np.log(E)
    logE -= logE.mean(axis=1, keepdims=True)                 # each tile's exposure
    M, N = shape
    g = np.linspace(0.0, 1.0, INTENSITY_TILT_GRID)
    X = pixel_coordinates_mm(g[:, None] * (M - 1), g[None, :] * (N - 1), shape, pixel_size_um).reshape(-1, 3)
    shading = lamp_vectors(X, intensities=np.exp(logE.mean(axis=0)), positions_mm=P[0])[..., 2]     # (K, G)
    out = {}
    for k, e in zip(names, logE):
        V = lamp_vectors(X, intensities=np.exp(e), positions_mm=P[0])                             # (K, G, 3)
        b = np.linalg.solve(np.einsum("kgi,kgj->gij", V, V), np.einsum("kgi,kg->gi", V, shading)[..., None])[..., 0]
        slope = np.mean(-b[:, :2] / b[:, 2:], axis=0)        # dz/dx, dz/dy (y up)
        out[k] = (float(slope[0] * (N - 1) / 2 * pixel_size_um), float(slope[1] * (M - 1) / 2 * pixel_size_um))
    return out


def align_rig_heights(heights: dict, corners: dict, pairs, levels: dict, *, degree: int = SHARED_DEGREE,
                      tilt_weight: Optional[float] = TILT_WEIGHT, shrink: bool = True, step: int = 4,
                      margin: int = 8) -> RigAlignment:
    """Per-tile offset and one error surface shared by every tile that make the tiles' heights agree.

    Under a rig (the lamps move with the camera) a bias of the lamps is the same in every tile, in the
    tile's own frame: each tile's height as integrated (``depth`` + what levelling removed, ``levels``)
    is the painting's, plus a constant, plus one surface ``E(u, v)`` common to all tiles. On an overlap
    two tiles see ``E`` at different places of their frames, so ``E``'s terms of total degree 2 to
    ``degree`` are measured by the overlaps (``E(u) - E(u + d)`` of a quadratic is a plane), while a
    free plane per tile would absorb them pair by pair and chain each tile's curvature error across the
    painting. One least squares over every used pair's overlap (sampled every ``step`` px, ``margin`` px
    in from both tiles' edges) finds the offsets, the tilts' corrections and ``E``: the overlaps set every
    relative tilt they measure, the tilts the normals measured (weighted ``tilt_weight``) only the rest
    (``E``'s quadratic against the painting's, one to the overlaps when the tilts are free). ``E`` is kept
    as far as it stands out of the tilts' noise (:func:`_shrunk_shared`), the rest solved again around
    it; then the painting-wide plane of the aligned surface is removed.

    Parameters
    ----------
    heights : dict
        ``{tile: (M, N) array}`` of the levelled heights (``depth.tif``; a memory map is read only where
        sampled); every tile of one shape.
    corners : dict
        The registered corners ``{tile: (x, y)}``.
    pairs : list of PairShift
        The registration's pairs (the used ones are aligned).
    levels : dict
        ``{tile: Legendre coefficients}`` of what levelling removed (``run.json`` ``level``'s
        ``legendre_coeffs_um``; ``raw = depth + legval2d(u, v, coeffs)``).
    degree : int
        Total degree of the shared surface (>= 2).
    tilt_weight : float or None
        Each tile's measured tilt's weight, a fraction of a tile's share of the overlap samples
        (:data:`TILT_WEIGHT`); None: the tilts held as measured.
    shrink : bool
        Keep ``E`` only as far as it stands out of the tilts' noise (with a ``tilt_weight``).

    Returns
    -------
    RigAlignment
    """
    names = list(heights)
    n, terms = len(names), _shared_terms(degree)
    m = len(terms)
    AtA, Atb, btb, count = _rig_normal_equations(heights, corners, pairs, levels, degree, step, margin)
    # the gauge (the offsets' sum 0); each tile's tilt held to what its normals measured, with the weight of
    # ``tilt_weight`` overlap samples (None: held exactly); a vanishing ridge for a term no overlap measures
    # (one row of tiles: no vertical curvature)
    reg = np.zeros_like(AtA)
    reg[0:3 * n:3, 0:3 * n:3] = 1e6
    tilts = np.r_[np.arange(1, 3 * n, 3), np.arange(2, 3 * n, 3)]
    reg[tilts, tilts] = 1e12 if tilt_weight is None else tilt_weight * max(count, 1) / max(n, 1)
    reg += 1e-9 * max(np.trace(AtA), 1.0) / len(Atb) * np.eye(len(Atb))
    sol, *_ = np.linalg.lstsq(AtA + reg, Atb, rcond=None)
    if shrink and tilt_weight is not None:
        # the shared surface as far as it stands out of the tilts' noise, then the rest solved again around it
        e = _shrunk_shared(AtA + reg, sol, tilts, reg[tilts, tilts], n)
        held, rhs = reg.copy(), Atb.copy()
        held[3 * n:, 3 * n:] += 1e12 * np.eye(m)
        rhs[3 * n:] += 1e12 * e
        sol, *_ = np.linalg.lstsq(AtA + held, rhs, rcond=None)
        sol[3 * n:] = e
    rms = float(np.sqrt(max(sol @ AtA @ sol - 2 * sol @ Atb + btb, 0.0) / count)) if count else float("nan")
    shared = np.zeros((degree + 1, degree + 1))
    for (i, j), e in zip(terms, sol[3 * n:]):
        shared[i, j] = e
    offsets = {k: float(sol[3 * i]) for i, k in enumerate(names)}
    forms = {}
    for i, k in enumerate(names):
        f = _pad(levels[k], degree) - _pad(shared, int(np.shape(levels[k])[0]) - 1)
        f[1, 0] += sol[3 * i + 1]
        f[0, 1] += sol[3 * i + 2]
        forms[k] = f
    plane = _painting_plane(heights, corners, forms, offsets, 4 * step, margin)
    return RigAlignment({k: (offsets[k] - plane[0], -plane[1], -plane[2]) for k in names}, forms, shared, offsets,
                        rms)


def _shrunk_shared(A, sol, tilts, w, n) -> np.ndarray:
    """The shared surface's terms shrunk toward zero by how far they stand out of the tilts' noise
    (empirical Bayes: a normal prior of zero mean whose variance is what the estimate holds beyond its
    noise; James and Stein 1961, Efron and Morris 1973).

    The overlaps set every relative tilt but the shared surface's part; that part comes from the tilts the
    tiles measured, weighted ``w`` in the normal matrix ``A``. The tilts' corrections ``sol[tilts]`` are their
    errors where the overlaps measure them (about ``2 n - 5`` of the ``2 n``: not the painting's common tilt
    nor the shared quadratic's three terms): their sum of squares over ``trace(R R^T)``, ``R`` the map
    from the tilts' errors to the corrections, is the tilts' noise, which the map to the shared terms
    carries to the estimate ``e``'s covariance ``C``. With no shared error
    (lamps that hold), ``e`` is that noise: its chi-square ``e^T C^-1 e`` below ``m`` times the
    :data:`SHARED_SIGNIFICANCE` quantile of F(m, dof) (the noise itself estimated), it is taken as zero, and
    each tile keeps the plane the overlaps give it."""
    m = len(sol) - 3 * n
    e = sol[3 * n:]
    if m == 0:
        return e
    if n < 3:
        # one pair: its overlap cannot tell the shared curvature from the two tiles' relative tilt, so the
        # estimate is the measured tilts' noise alone, with nothing to test it against
        return np.zeros(m)
    # how the tilts' errors reach the solution: an error e_t of a measured tilt acts as the tilt's prior
    # moved by e_t, so the corrections are -(I - R) e and the shared terms J e, with G = A^-1 w
    G = np.linalg.solve(A, np.eye(len(sol))[:, tilts] * w)
    R, J = np.eye(len(tilts)) - G[tilts], G[3 * n:]
    dof = float(np.sum(R * R))
    noise = float(sol[tilts] @ sol[tilts]) / max(dof, 1e-12)
    C = noise * J @ J.T
    chi2 = float(e @ np.linalg.lstsq(C, e, rcond=None)[0])
    log.info("mosaic heights: shared surface %s um, its noise %s um (tilts' noise %.3g um, chi2 %.3g on %d terms)",
             np.round(e, 3).tolist(), np.round(np.sqrt(np.diag(C)), 3).tolist(), np.sqrt(noise), chi2, m)
    # the noise is estimated from a few tilts' worth of degrees of freedom: chi2 / m is F(m, dof) distributed;
    # its quantile by scipy.special's fdtri, the value scipy.stats.f.ppf returns: importing scipy.stats cost the
    # batch's process 0.33 s of CPU while its workers start; scipy.special comes with scipy.ndimage
    from scipy.special import fdtri
    if dof < 1 or chi2 < m * fdtri(m, dof, SHARED_SIGNIFICANCE):
        return np.zeros(m)
    tau2 = max(0.0, (float(e @ e) - float(np.trace(C))) / m)
    return tau2 * np.linalg.solve(tau2 * np.eye(m) + C, e)


def _rig_normal_equations(heights, corners, pairs, levels, degree, step, margin):
    """:func:`align_rig_heights`'s normal equations over ``[offset, tilt_u, tilt_v]`` of each tile and
    the shared terms, pair by pair (a pair's rows touch its two tiles' columns and the shared ones
    alone), the right-hand side's sum of squares and the samples' count."""
    names = list(heights)
    idx = {k: i for i, k in enumerate(names)}
    n, m = len(names), len(_shared_terms(degree))
    AtA, Atb, btb, count = np.zeros((3 * n + m, 3 * n + m)), np.zeros(3 * n + m), 0.0, 0
    for p in pairs:
        if not p.used:
            continue
        ha, hb = heights[p.a], heights[p.b]
        (xa, ya), (xb, yb) = corners[p.a], corners[p.b]
        xy = _overlap_samples(ha, hb, (xa, ya), (xb, yb), step, margin)
        if xy is None:
            continue
        X, Y = xy
        va, vb = _raw_at(ha, levels[p.a], Y - ya, X - xa), _raw_at(hb, levels[p.b], Y - yb, X - xb)
        ok = np.isfinite(va) & np.isfinite(vb)
        X, Y, r = X[ok], Y[ok], (vb - va)[ok]
        # aligned, raw_t + o_t + tilt_t . (u, v) - E(in t's frame) agree:
        # [1, u, v]_a . (o, tilt)_a - [1, u, v]_b . (o, tilt)_b + (S_b - S_a) e = raw_b - raw_a
        ua, wa = legendre_uv(Y - ya, X - xa, ha.shape)
        ub, wb = legendre_uv(Y - yb, X - xb, hb.shape)
        one = np.ones(X.size)
        D = np.column_stack([one, ua, wa, -one, -ub, -wb,
                             _shared_basis(Y - yb, X - xb, hb.shape, degree)
                             - _shared_basis(Y - ya, X - xa, ha.shape, degree)])
        ix = np.r_[3 * idx[p.a] + np.arange(3), 3 * idx[p.b] + np.arange(3), 3 * n + np.arange(m)]
        AtA[np.ix_(ix, ix)] += D.T @ D
        Atb[ix] += D.T @ r
        btb += float(r @ r)
        count += X.size
    return AtA, Atb, btb, count


def _pad(coeffs, degree: int) -> np.ndarray:
    """Legendre coefficients padded with zeros to at least ``degree + 1`` a side."""
    c = np.asarray(coeffs, np.float64)
    d = max(c.shape[0], degree + 1)
    out = np.zeros((d, d))
    out[:c.shape[0], :c.shape[1]] = c
    return out


def _painting_plane(heights, corners, forms, offsets, step, margin) -> np.ndarray:
    """The least-squares plane ``(a, b, c)`` (painting pixels / :data:`PLANE_SCALE_PX`) of every tile's
    aligned height (``depth + form + offset``) on an inner grid of each tile."""
    from numpy.polynomial import legendre

    pts, vals = [], []
    for k, h in heights.items():
        M, N = h.shape
        rr, cc = np.meshgrid(np.arange(margin, M - margin, step), np.arange(margin, N - margin, step), indexing="ij")
        rr, cc = rr.ravel(), cc.ravel()
        u, v = legendre_uv(rr, cc, h.shape)
        z = np.asarray(h[rr, cc], np.float64) + legendre.legval2d(u, v, forms[k]) + offsets[k]
        ok = np.isfinite(z)
        X, Y = (cc[ok] + corners[k][0]) / PLANE_SCALE_PX, (rr[ok] + corners[k][1]) / PLANE_SCALE_PX
        pts.append(np.column_stack([np.ones(ok.sum()), X, Y]))
        vals.append(z[ok])
    plane, *_ = np.linalg.lstsq(np.vstack(pts), np.concatenate(vals), rcond=None)
    return plane
