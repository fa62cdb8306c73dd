"""Compare two protrusion detections (e.g. manual wand vs automated) per colour area.

The paper (Salvant et al., "Evaluation of the automated method", Fig. 4b-c) compares the
protrusions per cm^2 found by the two methods in each colour area and shows the manual ones the
automated method missed. Protrusions of table ``a`` and ``b`` are matched one-to-one by centroid
distance; per area the comparison gives the counts and densities of both, the matched pairs, the
``a`` protrusions without a partner (missed) and the ``b`` protrusions without one (extra).
"""
from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Optional

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from ..errors import UVPSInputError, check_pixel_size
from .regions import UM2_PER_CM2, RegionMap

log = logging.getLogger(__name__)

#: Columns of comparison.csv, in order.
COLUMNS = ("label", "name", "area_cm2", "count_a", "count_b", "density_a", "density_b",
           "matched", "missed", "extra")


@dataclass
class Comparison:
    """Result of :func:`compare_detections`.

    Attributes
    ----------
    pairs : (P, 2) int ndarray
        Matched row indices ``(i_a, i_b)`` into the two tables.
    distance_um : (P,) ndarray
        Centroid distance of each pair.
    missed : ndarray
        Row indices of ``a`` without a partner.
    extra : ndarray
        Row indices of ``b`` without a partner.
    rows : list of dict
        Per area (then "all"): the columns of :data:`COLUMNS`.
    name_a, name_b : str
        What the two tables are (e.g. "manual", "automated").
    """

    pairs: np.ndarray
    distance_um: np.ndarray
    missed: np.ndarray
    extra: np.ndarray
    rows: list = field(default_factory=list)
    name_a: str = "a"
    name_b: str = "b"


def _xy_w(table, what):
    for c in ("x_px", "y_px", "width_um"):
        if c not in table:
            raise UVPSInputError(f"table {what} lacks column {c}")
    x = np.asarray(table["x_px"], float)
    y = np.asarray(table["y_px"], float)
    w = np.asarray(table["width_um"], float)
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise UVPSInputError(f"table {what}: x_px and y_px must be finite numbers")
    return np.column_stack([x, y]), np.nan_to_num(w, nan=0.0)


def match_protrusions(xy_a, w_a, xy_b, w_b, *, pixel_size_um: float,
                      match_radius_um: Optional[float] = None):
    """One-to-one matching of centroids within a radius that maximises the matches.

    Candidate pairs are those within the radius (``cKDTree.sparse_distance_matrix`` with the largest
    radius, then the per-pair radius ``max(2 px, 0.5 x the larger width)`` unless
    ``match_radius_um`` is given). The candidate graph splits into connected components; on each,
    :func:`scipy.optimize.linear_sum_assignment` runs with a prohibitive cost on non-candidates,
    so it first maximises the number of matches, then minimises their total distance.

    Returns
    -------
    pairs : (P, 2) int ndarray and distances (P,) in um
    """
    na, nb = len(xy_a), len(xy_b)
    if na == 0 or nb == 0:
        return np.zeros((0, 2), int), np.zeros(0)
    px = float(pixel_size_um)
    if match_radius_um is None:
        r_max = max(2.0 * px, 0.5 * max(w_a.max(), w_b.max()))
    else:
        r_max = float(match_radius_um)
    tree_a, tree_b = cKDTree(xy_a * px), cKDTree(xy_b * px)
    cand = tree_a.sparse_distance_matrix(tree_b, r_max, output_type="ndarray")
    ia, ib, d = cand["i"].astype(int), cand["j"].astype(int), cand["v"].astype(float)
    if match_radius_um is None:
        ok = d <= np.maximum(2.0 * px, 0.5 * np.maximum(w_a[ia], w_b[ib]))
    else:
        ok = d <= r_max
    ia, ib, d = ia[ok], ib[ok], d[ok]
    if len(ia) == 0:
        return np.zeros((0, 2), int), np.zeros(0)
    graph = coo_matrix((np.ones(len(ia)), (ia, na + ib)), shape=(na + nb, na + nb))
    _, comp = connected_components(graph, directed=False)
    pairs, dists = [], []
    big = 1e6 * (r_max + 1.0)
    for c in np.unique(comp[ia]):
        sel = comp[ia] == c
        ua, inv_a = np.unique(ia[sel], return_inverse=True)
        ub, inv_b = np.unique(ib[sel], return_inverse=True)
        cost = np.full((len(ua), len(ub)), big)
        cost[inv_a, inv_b] = d[sel]
        ra, rb = linear_sum_assignment(cost)
        keep = cost[ra, rb] < big
        pairs.extend(zip(ua[ra[keep]], ub[rb[keep]]))
        dists.extend(cost[ra[keep], rb[keep]])
    order = np.argsort([p[0] for p in pairs], kind="stable")
    return np.array(pairs, int).reshape(-1, 2)[order], np.array(dists, float)[order]


def compare_detections(a, b, *, regions: Optional[RegionMap], pixel_size_um: float,
                       match_radius_um: Optional[float] = None, name_a: str = "a",
                       name_b: str = "b") -> Comparison:
    """Match two protrusion tables one-to-one and count matched / missed / extra per area.

    Parameters
    ----------
    a, b : dict
        Protrusion tables with ``x_px``, ``y_px`` and ``width_um`` (``a`` is the reference, e.g.
        the manual wand selection of the paper; ``b`` the automated detection).
    regions : RegionMap or None
        Colour areas; each protrusion belongs to the area at its centroid. None: only the "all"
        row, without area or densities.
    pixel_size_um : float
        Pixel size in micrometres.
    match_radius_um : float, optional
        Largest centroid distance of a match. Default per pair: ``max(2 px, 0.5 x the larger
        width)``, i.e. the centroids lie within the larger protrusion.
    name_a, name_b : str
        Labels of the two tables (for reports).

    Returns
    -------
    Comparison
        ``rows``: per area ``count_a``, ``count_b``, ``density_a``, ``density_b`` (per cm^2),
        ``matched`` (pairs whose ``a`` protrusion is in the area), ``missed`` (``a`` without a
        partner), ``extra`` (``b`` without a partner); so ``count_a = matched + missed``, while
        ``count_b`` may differ from ``matched + extra`` when a pair straddles an area border.

    Examples
    --------
    >>> import numpy as np
    >>> a = {"x_px": np.array([10.0, 50.0]), "y_px": np.array([10.0, 10.0]),
    ...      "width_um": np.array([200.0, 200.0])}
    >>> b = {"x_px": np.array([11.0]), "y_px": np.array([10.0]), "width_um": np.array([180.0])}
    >>> c = compare_detections(a, b, regions=None, pixel_size_um=15.0)
    >>> c.pairs.tolist(), c.missed.tolist(), c.extra.tolist()
    ([[0, 0]], [1], [])
    """
    pixel_size_um = check_pixel_size(pixel_size_um)
    if match_radius_um is not None and not (np.isfinite(match_radius_um) and match_radius_um > 0):
        raise UVPSInputError(f"match_radius_um must be a positive number or null; "
                             f"got {match_radius_um}")
    xy_a, w_a = _xy_w(a, name_a)
    xy_b, w_b = _xy_w(b, name_b)
    pairs, dist = match_protrusions(xy_a, w_a, xy_b, w_b, pixel_size_um=pixel_size_um,
                                    match_radius_um=match_radius_um)
    matched_a = np.zeros(len(xy_a), bool)
    matched_a[pairs[:, 0]] = True
    matched_b = np.zeros(len(xy_b), bool)
    matched_b[pairs[:, 1]] = True
    if regions is not None:
        reg_a = regions.at(xy_a[:, 0], xy_a[:, 1])
        reg_b = regions.at(xy_b[:, 0], xy_b[:, 1])
        area_px = regions.area_px()
        areas = [(i, regions.names[i], area_px[i] * pixel_size_um**2 / UM2_PER_CM2)
                 for i in regions.ids]
        total = sum(x[2] for x in areas)
        ids = regions.ids
        in_a, in_b = np.isin(reg_a, ids), np.isin(reg_b, ids)
    else:
        reg_a = np.zeros(len(xy_a), int)
        reg_b = np.zeros(len(xy_b), int)
        areas, total = [], float("nan")
        in_a, in_b = np.ones(len(xy_a), bool), np.ones(len(xy_b), bool)
    rows = [_row(i, name, area, reg_a == i, reg_b == i, matched_a, matched_b)
            for i, name, area in areas]
    rows.append(_row("all", "all areas" if regions is not None else "whole image", total,
                     in_a, in_b, matched_a, matched_b))
    log.info("compare: %d matched, %d missed, %d extra", len(pairs), int((~matched_a).sum()),
             int((~matched_b).sum()))
    return Comparison(pairs, dist, np.flatnonzero(~matched_a), np.flatnonzero(~matched_b),
                      rows, name_a, name_b)


def _row(label, name, area_cm2, sel_a, sel_b, matched_a, matched_b) -> dict:
    count_a, count_b = int(sel_a.sum()), int(sel_b.sum())
    known = bool(np.isfinite(area_cm2) and area_cm2 > 0)

    def dens(n):
        return n / area_cm2 if known else float("nan")

    return {"label": label, "name": name, "area_cm2": float(area_cm2), "count_a": count_a,
            "count_b": count_b, "density_a": dens(count_a), "density_b": dens(count_b),
            "matched": int((sel_a & matched_a).sum()), "missed": int((sel_a & ~matched_a).sum()),
            "extra": int((sel_b & ~matched_b).sum())}
