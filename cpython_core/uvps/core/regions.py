"""Colour areas: user labels or masks, an automatic proposal, and per-area protrusion statistics.

The paper (Salvant et al., "Manual Protrusion Detection" and "Results", Fig. 3c-d and 4a) segments
the painting into areas of one paint colour and reports, per area, the number of protrusions per
cm^2 as a function of their width (100 um bins). A :class:`RegionMap` is an (M, N) label image
(0 = no area) with a name per area; it is read from a label TIFF or a list of masks, or proposed
from the albedo colour by :func:`propose_regions`, and written as ``regions_labels.tif`` (opens in
ImageJ) with the names in ``regions.csv`` beside it.
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import NamedTuple, Optional, Union

import numpy as np
from scipy import ndimage as ndi
from skimage.measure import label as cc_label

# The proposal's libraries (cv2, scipy.cluster, skimage.color / filters.rank / morphology / transform) are
# imported by the functions that use them: a run without --regions auto reads region statistics only,
# and does not pay their ~0.1-0.2 s of start-up (python -X importtime -m uvps run --help).

from ..errors import UVPSInputError, check_pixel_size
from .progress import report

log = logging.getLogger(__name__)

#: um^2 per cm^2.
UM2_PER_CM2 = 1e8


@dataclass
class RegionMap:
    """Colour areas of a capture.

    Attributes
    ----------
    labels : (M, N) int32
        Area label per pixel, 0 = in no area.
    names : dict of int -> str
        A name per area label present in ``labels``.
    colors : dict of int -> (3,) float, optional
        Mean albedo colour of each area scaled to 0..1 (for figures), when known.
    """

    labels: np.ndarray
    names: dict
    colors: dict = field(default_factory=dict)

    @property
    def ids(self) -> list:
        """Area labels in increasing order."""
        return sorted(self.names)

    def area_px(self) -> dict:
        """Pixel count per area label."""
        counts = np.bincount(self.labels.ravel(), minlength=max(self.ids, default=0) + 1)
        return {i: int(counts[i]) for i in self.ids}

    def at(self, x_px, y_px) -> np.ndarray:
        """Area label at the pixels containing points ``(x_px, y_px)`` (0 = none or outside)."""
        x = np.asarray(x_px, dtype=float)
        y = np.asarray(y_px, dtype=float)
        M, N = self.labels.shape
        out = np.zeros(x.shape, dtype=np.int64)
        ok = np.isfinite(x) & np.isfinite(y)
        r = np.rint(np.where(ok, y, -1)).astype(int)
        c = np.rint(np.where(ok, x, -1)).astype(int)
        ok &= (r >= 0) & (r < M) & (c >= 0) & (c < N)
        out[ok] = self.labels[r[ok], c[ok]]
        return out


def whole_image(shape, name: str = "whole image") -> RegionMap:
    """One area covering the whole image (used when no colour areas are given)."""
    return RegionMap(np.ones(tuple(shape), np.int32), {1: name})


def _as_label_image(arr: np.ndarray, what: str) -> np.ndarray:
    arr = np.asarray(arr)
    if arr.ndim > 2 and sum(n != 1 for n in arr.shape) == 2:
        arr = arr.reshape([n for n in arr.shape if n != 1])  # a single-plane stack
    if arr.ndim != 2:
        raise UVPSInputError(f"{what} must be a 2-D label image; got shape {arr.shape}")
    if np.issubdtype(arr.dtype, np.floating):
        if not np.all(np.isfinite(arr)) or np.any(arr != np.round(arr)):
            raise UVPSInputError(f"{what} must hold whole-number labels; got fractional or "
                                 "NaN values")
    elif not (np.issubdtype(arr.dtype, np.integer) or arr.dtype == np.bool_):
        raise UVPSInputError(f"{what} must be an integer label image; got {arr.dtype}")
    if arr.size and arr.min() < 0:
        raise UVPSInputError(f"{what} must hold labels >= 0 (0 = no area); got {arr.min()}")
    return arr.astype(np.int32)


def _check_shape(arr: np.ndarray, shape, what: str) -> None:
    if arr.shape != tuple(shape):
        raise UVPSInputError(f"{what} is {arr.shape[0]} x {arr.shape[1]} pixels; expected the "
                             f"capture's {shape[0]} x {shape[1]}")


def _mask_of(arr: np.ndarray, shape, what: str) -> np.ndarray:
    arr = np.asarray(arr)
    if arr.ndim == 3 and arr.shape[-1] in (3, 4) and arr.shape[:2] == tuple(shape):
        arr = arr[..., :3].any(axis=-1)
    elif arr.ndim == 3 and arr.shape[0] in (3, 4) and arr.shape[1:] == tuple(shape):
        arr = arr[:3].any(axis=0)
    if arr.ndim != 2:
        raise UVPSInputError(f"{what} must be a 2-D mask; got shape {arr.shape}")
    _check_shape(arr, shape, what)
    return arr != 0


# ---------------------------------------------------------------------------------------------
# automatic proposal


@dataclass
class ProposalOptions:
    """Options of :func:`propose_regions`.

    Attributes
    ----------
    smooth_mm : float
        Scale of the smoothing (majority filter diameter): protrusions (<= 0.5 mm) and brush
        texture below it do not form their own areas.
    min_area_mm2 : float
        Islands smaller than this join the surrounding area.
    delta_e : float
        When ``n_areas`` is None: clusters whose mean colours differ by less than this CIE76
        colour difference (Lab units) are merged.
    max_areas : int
        Largest number of areas tried when ``n_areas`` is None.
    sample : int
        Pixels sampled for k-means.
    """

    smooth_mm: float = 1.0
    min_area_mm2: float = 1.0
    delta_e: float = 7.0
    max_areas: int = 8
    sample: int = 20000


def _srgb_encode(linear: np.ndarray) -> np.ndarray:
    # Hand-written: skimage.color.rgb2lab expects sRGB-encoded values and offers no public
    # linear-RGB entry; this is the IEC 61966-2-1 transfer function.
    linear = np.clip(linear, 0.0, 1.0)
    return np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * linear ** (1 / 2.4) - 0.055)


def _kmeans(data: np.ndarray, k: int, seed: int):
    import cv2

    cv2.setRNGSeed(int(seed))
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    _, lab, centres = cv2.kmeans(data.astype(np.float32), int(k), None, criteria, 3,
                                 cv2.KMEANS_PP_CENTERS)
    return centres.astype(np.float64), lab.ravel()


def _merge_close(centres: np.ndarray, delta_e: float) -> np.ndarray:
    """Group index per centre: average-linkage clustering of the centres cut at ``delta_e``."""
    if len(centres) < 2:
        return np.zeros(len(centres), dtype=int)
    from scipy.cluster.hierarchy import fcluster, linkage

    z = linkage(centres, method="average")
    return fcluster(z, t=delta_e, criterion="distance") - 1


def propose_regions(albedo, *, pixel_size_um: float, n_areas: Optional[int] = None, mask=None,
                    seed: int = 0, options: Optional[ProposalOptions] = None,
                    progress=None) -> RegionMap:
    """Propose colour areas by clustering the albedo colour, smoothed at about 1 mm.

    Parameters
    ----------
    albedo : (M, N), (3, M, N) or (M, N, 3) ndarray
        Albedo (linear); grey albedo clusters on lightness only.
    pixel_size_um : float
        Pixel size in micrometres (sets the smoothing scale).
    n_areas : int, optional
        Number of areas; None chooses it (clusters closer than ``options.delta_e`` merge).
    mask : (M, N) bool ndarray, optional
        Pixels to segment (True); the rest get label 0.
    seed : int
        Seed of the k-means initialisation (k-means++).
    options : ProposalOptions, optional
    progress : callable(fraction, message), optional

    Returns
    -------
    RegionMap
        Areas labelled 1.. in decreasing lightness, named "area k", with their mean colours.

    Notes
    -----
    The albedo is block-averaged over its valid pixels to about 1/9 of ``smooth_mm`` per block
    (``skimage.transform.downscale_local_mean``; this also averages noise and protrusions away),
    scaled by the pixels' 99.5th percentile, sRGB-encoded and converted to CIE Lab
    (``skimage.color.rgb2lab``), clustered with k-means (``cv2.kmeans``, k-means++) on a
    sample of blocks, each block assigned to the nearest centre, majority-filtered
    (``skimage.filters.rank.majority``) over a disc of ``smooth_mm`` diameter, islands under
    ``min_area_mm2`` join their nearest neighbour area, and the map is scaled back to full size
    (nearest neighbour). It is a proposal: the user
    edits ``regions_labels.tif`` in ImageJ and loads it back with :func:`load_regions`.
    """
    from skimage.color import rgb2lab

    opts = options or ProposalOptions()
    pixel_size_um = check_pixel_size(pixel_size_um)
    if n_areas is not None and (int(n_areas) != n_areas or n_areas < 1):
        raise UVPSInputError(f"n_areas must be a positive integer or None; got {n_areas}")
    shape, channels = _albedo_channels(albedo)
    extent_mm = max(shape) * pixel_size_um / 1000.0
    if extent_mm < opts.smooth_mm:
        # One smoothing block would hold the whole image: nothing to cluster (k-means on one
        # sample fails deep in scipy). A pixel size typed in mm instead of um lands here.
        raise UVPSInputError(
            f"pixel_size_um {pixel_size_um:g} makes the {shape[1]} x {shape[0]} px image "
            f"{extent_mm:.3g} mm wide, smaller than the {opts.smooth_mm:g} mm over which colour "
            "areas are proposed; give the pixel size in micrometres (0.1 mm = 100 um) or the "
            "areas as a label image")
    grey = len(channels) == 1
    valid = _valid_pixels(channels, shape, mask)
    # Everything but the final label map is computed on blocks of about smooth_mm / 9: block
    # means over the valid pixels (also averaging noise and protrusions away), so a large capture
    # never needs a full-size float copy.
    report(progress, 0.05, "block means")
    step = max(1, int(round(opts.smooth_mm * 1000.0 / 9.0 / pixel_size_um)))
    blocks = _block_means(channels, valid, step)
    scale = _albedo_scale(channels, valid)
    report(progress, 0.15, "colour space")
    lab = rgb2lab(_srgb_encode(blocks.rgb / scale))
    feats = lab[..., :1] if grey else lab
    sampled = blocks.mostly_valid if blocks.mostly_valid.any() else blocks.any_valid
    data = _feature_sample(feats[sampled], opts.sample, seed)
    report(progress, 0.3, "k-means")
    centres = _colour_centres(data, n_areas, opts, seed)
    small_lab = _nearest_centre(feats, centres, blocks.any_valid)
    report(progress, 0.6, "smoothing")
    radius = max(1, int(round(opts.smooth_mm * 1000.0 / 2.0 / (pixel_size_um * step))))
    smooth = _majority_filter(small_lab, blocks.any_valid, radius)
    min_blocks = opts.min_area_mm2 * 1e6 / (pixel_size_um * step) ** 2
    smooth = _absorb_islands(smooth, blocks.any_valid, min_blocks)
    smooth, n_found = _relabel_by_lightness(smooth, lab[..., 0])
    colors = {new: np.clip(blocks.rgb[smooth == new].mean(axis=0) / scale, 0.0, 1.0)
              for new in range(1, n_found + 1)}
    report(progress, 0.85, "full size")
    full = _full_size(smooth, step, shape, valid)
    report(progress, 1.0, f"{n_found} areas")
    log.info("proposed %d colour areas (block %d px, majority radius %d)", n_found, step, radius)
    return RegionMap(full, {i: f"area {i}" for i in range(1, n_found + 1)}, colors)


def _albedo_channels(albedo):
    """Image shape (M, N) and the albedo's channels: one (grey) or three (M, N) arrays."""
    arr = np.asarray(albedo)
    if arr.ndim == 2:
        return arr.shape, [arr]
    if arr.ndim == 3 and arr.shape[0] == 3:
        return arr.shape[1:], [arr[c] for c in range(3)]
    if arr.ndim == 3 and arr.shape[-1] == 3:
        return arr.shape[:2], [arr[..., c] for c in range(3)]
    raise UVPSInputError(f"albedo must be (M, N), (3, M, N) or (M, N, 3); got {arr.shape}")


def _valid_pixels(channels, shape, mask) -> np.ndarray:
    """Pixels finite in every channel and inside ``mask``; at least one, or bad input."""
    valid = np.ones(shape, bool)
    for ch in channels:
        valid &= np.isfinite(ch)
    if mask is not None:
        mask = np.asarray(mask)
        _check_shape(mask, shape, "mask")
        valid &= mask.astype(bool)
    if not valid.any():
        raise UVPSInputError("propose_regions: no valid pixel (mask empty or albedo all NaN)")
    return valid


class _Blocks(NamedTuple):
    """Block means of the albedo over its valid pixels."""

    rgb: np.ndarray  # (R, C, 3) mean colour (grey repeated to 3 channels)
    any_valid: np.ndarray  # (R, C) bool: the block holds a valid pixel
    mostly_valid: np.ndarray  # (R, C) bool: more than half of the block's pixels are valid


def _block_means(channels, valid, step) -> _Blocks:
    from skimage.transform import downscale_local_mean

    count = downscale_local_mean(valid.astype(np.float32), (step, step))
    any_valid = count > 0
    sums = [downscale_local_mean(np.where(valid, ch, 0).astype(np.float32), (step, step))
            for ch in channels]
    rgb = np.stack([sm / np.where(any_valid, count, 1.0) for sm in sums], axis=-1)
    if len(channels) == 1:
        rgb = np.repeat(rgb, 3, axis=-1)
    return _Blocks(rgb, any_valid, count > 0.5)


def _albedo_scale(channels, valid) -> float:
    """The valid pixels' 99.5th percentile (as the report displays the albedo), on a subsample."""
    sub = max(1, int(np.sqrt(valid.size / 1e6)))
    sample_px = np.stack([ch[::sub, ::sub] for ch in channels], axis=-1)[valid[::sub, ::sub]]
    scale = float(np.percentile(sample_px, 99.5)) if sample_px.size else 0.0
    return scale if np.isfinite(scale) and scale > 0 else 1.0


def _feature_sample(data, sample: int, seed: int) -> np.ndarray:
    """At most ``sample`` rows of ``data``, drawn without replacement."""
    rng = np.random.default_rng(seed)
    if len(data) > sample:
        data = data[rng.choice(len(data), sample, replace=False)]
    return data


def _colour_centres(data, n_areas, opts: ProposalOptions, seed: int) -> np.ndarray:
    """Cluster centres in Lab: ``n_areas`` of them, or when None up to ``opts.max_areas`` with
    centres closer than ``opts.delta_e`` merged (weighted by their members)."""
    n_distinct = len(np.unique(np.round(data, 3), axis=0))
    if n_areas is not None:
        centres, _ = _kmeans(data, min(int(n_areas), n_distinct), seed)
        return centres
    k = min(opts.max_areas, n_distinct)
    centres, assigned = _kmeans(data, k, seed)
    groups = _merge_close(centres, opts.delta_e)
    weights = np.bincount(assigned, minlength=k).astype(float)
    return np.array([np.average(centres[groups == g], axis=0, weights=weights[groups == g])
                     if weights[groups == g].sum() > 0 else centres[groups == g].mean(0)
                     for g in range(groups.max() + 1)])


def _nearest_centre(feats, centres, any_valid) -> np.ndarray:
    """uint16 label 1.. of each block's nearest centre (0 in blocks without a valid pixel)."""
    from scipy.cluster.vq import vq

    flat = feats.reshape(-1, feats.shape[-1])
    nearest, _ = vq(flat, centres.astype(flat.dtype))
    labels = (nearest + 1).reshape(feats.shape[:2]).astype(np.uint16)
    labels[~any_valid] = 0
    return labels


def _majority_filter(labels, any_valid, radius: int) -> np.ndarray:
    """Majority filter over a disc of ``radius`` blocks, within the blocks holding a valid pixel."""
    from skimage.filters.rank import majority
    from skimage.morphology import disk

    smooth = majority(labels, disk(radius), mask=any_valid)
    smooth[~any_valid] = 0
    return smooth


def _absorb_islands(smooth, any_valid, min_blocks: float) -> np.ndarray:
    """Islands under ``min_blocks`` blocks join their nearest other area.

    Hand-written fill: no library merges small label components into their neighbours.
    """
    comps = cc_label(smooth, background=0, connectivity=1)
    sizes = np.bincount(comps.ravel())
    tiny = (sizes < min_blocks)[comps] & (comps > 0)
    if tiny.any() and (~tiny & any_valid).any():
        keep = ~tiny & (smooth > 0)
        idx = ndi.distance_transform_edt(~keep, return_distances=False, return_indices=True)
        smooth = np.where(tiny, smooth[idx[0], idx[1]], smooth)
    return smooth


def _relabel_by_lightness(smooth, lightness):
    """Labels 1.. by decreasing mean lightness, dropping areas that vanished: (labels, count)."""
    present = [int(i) for i in np.unique(smooth) if i != 0]
    order = sorted(present, key=lambda i: -float(np.mean(lightness[smooth == i])))
    lut = np.zeros(int(smooth.max()) + 1, np.int32)
    for new, old in enumerate(order, start=1):
        lut[old] = new
    return lut[smooth], len(order)


def _full_size(smooth, step: int, shape, valid) -> np.ndarray:
    """The block label map scaled back to the image (nearest neighbour), 0 off the valid pixels."""
    full = np.repeat(np.repeat(smooth, step, axis=0), step, axis=1)[: shape[0], : shape[1]]
    full = full.astype(np.int32)
    full[~valid] = 0
    return full


# ---------------------------------------------------------------------------------------------
# statistics


@dataclass
class AreaStats:
    """Protrusion statistics of one colour area (or of all areas together: label ``"all"``)."""

    label: Union[int, str]
    name: str
    area_cm2: float
    count: int
    density_per_cm2: float
    counts: np.ndarray  # per width bin
    densities: np.ndarray  # per width bin, per cm^2


@dataclass
class RegionStats:
    """Per-area statistics and the width bin edges (um) they share; ``rows[-1]`` is "all"."""

    edges_um: np.ndarray
    rows: list
    outside: int = 0  # protrusions in no area


def bin_edges(bins_um, max_width: float) -> np.ndarray:
    """Width bin edges from a bin width (equal bins from 0 covering ``max_width``) or edges."""
    if np.ndim(bins_um) == 0:
        w = float(bins_um)
        if not (np.isfinite(w) and w > 0):
            raise UVPSInputError(f"bins_um must be a positive width or increasing edges; "
                                 f"got {bins_um}")
        n = max(1, int(np.floor(max_width / w)) + 1) if np.isfinite(max_width) else 1
        return np.arange(n + 1) * w
    edges = np.asarray(bins_um, dtype=float)
    if edges.ndim != 1 or len(edges) < 2 or np.any(np.isnan(edges)) or np.any(np.diff(edges) <= 0):
        raise UVPSInputError(f"bins_um edges must be at least 2 strictly increasing numbers; "
                             f"got {list(np.atleast_1d(edges))}")
    return edges


def _area_row(label, name, area_cm2, widths, edges) -> AreaStats:
    counts = np.histogram(widths, bins=edges)[0] if len(widths) else np.zeros(len(edges) - 1, int)
    return AreaStats(label, name, area_cm2, int(len(widths)), len(widths) / area_cm2,
                     counts.astype(np.int64), counts / area_cm2)


def region_statistics(table, regions: RegionMap, *, pixel_size_um: float,
                      bins_um=100.0) -> RegionStats:
    """Protrusions per cm^2 per colour area, in total and per width bin (paper Fig. 4a).

    Parameters
    ----------
    table : dict
        Protrusion table (``x_px``, ``y_px``, ``width_um``) from
        :func:`uvps.core.measure.measure_protrusions` or :func:`uvps.files.tables.read_protrusions_csv`.
    regions : RegionMap
        Colour areas; a protrusion belongs to the area at its rounded centroid.
    pixel_size_um : float
        Pixel size in micrometres (area of an area = pixels x pixel_size^2).
    bins_um : float or sequence of float
        A bin width (equal bins from 0 up past the widest protrusion) or increasing bin edges
        (e.g. ``[0, 50, 100, 200, 300, inf]``); widths outside the edges count in the totals only.

    Returns
    -------
    RegionStats
        One row per area (increasing label) and a last row ``"all"`` (all areas together).

    Examples
    --------
    >>> import numpy as np
    >>> regions = RegionMap(np.ones((200, 200), np.int32), {1: "beige"})  # 1 cm^2 at 50 um
    >>> table = {"x_px": np.array([10.0, 20.0]), "y_px": np.array([5.0, 5.0]),
    ...          "width_um": np.array([150.0, 420.0])}
    >>> s = region_statistics(table, regions, pixel_size_um=50.0, bins_um=100.0)
    >>> s.rows[0].density_per_cm2, s.rows[0].counts.tolist()
    (2.0, [0, 1, 0, 0, 1])
    """
    if not isinstance(regions, RegionMap):
        raise UVPSInputError(f"regions must be a RegionMap; got {type(regions).__name__}")
    pixel_size_um = check_pixel_size(pixel_size_um)
    for c in ("x_px", "y_px", "width_um"):
        if c not in table:
            raise UVPSInputError(f"protrusion table lacks column {c}")
    widths = np.asarray(table["width_um"], dtype=float)
    where = regions.at(table["x_px"], table["y_px"])
    finite = widths[np.isfinite(widths)]
    edges = bin_edges(bins_um, float(finite.max()) if finite.size else 0.0)
    px_cm2 = pixel_size_um**2 / UM2_PER_CM2
    area_px = regions.area_px()
    rows = []
    for i in regions.ids:
        if area_px[i] == 0:
            raise UVPSInputError(f"colour area {i} ({regions.names[i]}) has no pixels")
        rows.append(_area_row(i, regions.names[i], area_px[i] * px_cm2, widths[where == i], edges))
    inside = np.isin(where, regions.ids)
    total_cm2 = sum(area_px.values()) * px_cm2
    rows.append(_area_row("all", "all areas", total_cm2, widths[inside], edges))
    outside = int((~inside).sum())
    if outside:
        log.info("%d protrusions lie in no colour area", outside)
    return RegionStats(edges, rows, outside)


def _edge_text(v: float) -> str:
    return "inf" if np.isinf(v) else f"{v:g}"


def bin_names(edges) -> list:
    """Column suffixes of the width bins, e.g. ``"0-100um"``."""
    return [f"{_edge_text(a)}-{_edge_text(b)}um" for a, b in zip(edges[:-1], edges[1:])]


def stats_columns(stats: RegionStats) -> dict:
    """The statistics as a column table (the layout of ``regions.csv``)."""
    names = bin_names(stats.edges_um)
    cols = {"label": [r.label for r in stats.rows], "name": [r.name for r in stats.rows],
            "area_cm2": [r.area_cm2 for r in stats.rows], "count": [r.count for r in stats.rows],
            "density_per_cm2": [r.density_per_cm2 for r in stats.rows]}
    for j, b in enumerate(names):
        cols[f"count_{b}"] = [int(r.counts[j]) for r in stats.rows]
    for j, b in enumerate(names):
        cols[f"density_{b}"] = [float(r.densities[j]) for r in stats.rows]
    return cols
