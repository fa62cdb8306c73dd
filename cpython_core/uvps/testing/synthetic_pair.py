"""Two captures of one painting some time apart (:func:`make_capture_pair`): protrusions grown, new
and gone, the later one seen from a slightly moved camera.

Part of :mod:`uvps.testing.synthetic`, which exposes every public name; import from there.
"""
from __future__ import annotations

import dataclasses
import math
import zlib
from dataclasses import dataclass
from typing import Optional

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree

from ..files.outputs import Progress, report
from .synthetic_spec import (
    Nuisances,
    PROTRUSION_COLOUR,
    SyntheticCapture,
    SyntheticSpec,
    _UM2_PER_CM2,
    _checked_overrides,
    logger,
)
from .synthetic_render import (
    _lamp_and_lens_nuisances,
    _peak,
    _shading,
    light_positions,
    normals_from_height,
    render_images,
)
from .synthetic_surface import _dome_profile, _protrusion_widths
from .synthetic_capture import make_capture


# --------------------------------------------------------------------------------------------
# A later capture of the same surface (monitoring over time; uvps changes)
# --------------------------------------------------------------------------------------------


@dataclass
class LaterSpec:
    """How a later capture differs from the first (:func:`make_capture_pair`).

    The camera: B's pixel ``(x=col, y=row)`` maps to A's by a similarity about the image centre,
    ``x_a = scale R(rotation_deg) (x_b - c) + c + shift_px``; None draws each within its bound
    (shift up to ``max_shift_px`` in a random direction, rotation within +-``max_rotation_deg``,
    scale within 1 +- ``max_scale_change``). One B pixel spans ``scale`` A pixels, so B's pixel
    size is ``scale`` x A's. The lamps are drawn anew (another session). The surface:
    ``grown_fraction`` of the lone protrusions (domes, craters, mesas with room around them)
    grow by a factor of ``width_growth`` in width and ``height_growth`` in height,
    ``new_per_cm2`` new domes of ``new_width_um`` erupt where there is room, and
    ``gone_fraction`` of them are gone (flattened to the paint around them). :meth:`unchanged`
    is the same surface, only another pose and other lamps.
    """

    shift_px: Optional[tuple] = None
    rotation_deg: Optional[float] = None
    scale: Optional[float] = None
    max_shift_px: float = 200.0
    max_rotation_deg: float = 3.0
    max_scale_change: float = 0.02
    grown_fraction: float = 0.25
    width_growth: tuple = (1.2, 1.5)
    height_growth: tuple = (1.2, 1.6)
    new_per_cm2: float = 4.0
    new_width_um: tuple = (40.0, 400.0)
    gone_fraction: float = 0.04
    seed: int = 1

    @classmethod
    def unchanged(cls, **fields) -> "LaterSpec":
        """Another pose and other lamps, the surface as it was (the repeatability pair)."""
        return cls(**{"grown_fraction": 0.0, "new_per_cm2": 0.0, "gone_fraction": 0.0, **fields})


@dataclass
class CapturePair:
    """Two captures of one surface and the truth of what changed (:func:`make_capture_pair`).

    ``b_to_a`` (3, 3) takes B pixel coordinates ``(x=col, y=row, 1)`` to A's. ``changes`` holds
    equal-length columns, one row per protrusion in A's or B's field: ``id_a``, ``id_b`` (1-based
    rows of ``a.protrusions`` / ``b.protrusions``, 0 where absent), ``x_px_a``, ``y_px_a``,
    ``x_px_b``, ``y_px_b``, ``status`` (new, grown, unchanged, gone), ``width_um_a``,
    ``width_um_b``, ``height_um_a``, ``height_um_b`` (NaN where absent).
    """

    a: SyntheticCapture
    b: SyntheticCapture
    b_to_a: np.ndarray
    changes: dict
    later: LaterSpec
    info: dict


def similarity_matrix(shape, *, shift_px=(0.0, 0.0), rotation_deg=0.0, scale=1.0) -> np.ndarray:
    """The 3 x 3 matrix ``b_to_a`` of a camera rotated and scaled about the centre of a
    ``shape`` (M, N) image and shifted by ``shift_px`` (x, y) pixels.

    >>> T = similarity_matrix((100, 200), shift_px=(5.0, -2.0))
    >>> (T @ [10.0, 10.0, 1.0]).tolist()
    [15.0, 8.0, 1.0]
    """
    m, n = shape
    c = np.array([(n - 1) / 2.0, (m - 1) / 2.0])
    t = math.radians(rotation_deg)
    lin = scale * np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])
    out = np.eye(3)
    out[:2, :2] = lin
    out[:2, 2] = c - lin @ c + np.asarray(shift_px, float)
    return out


def _ellipse(prot, i, px, shape, grow=1.0, reach=1.6):
    """Window, coordinates and elliptical radius of protrusion ``i`` (grown ``grow`` x)."""
    w, asp, phi = prot["width_um"][i], prot["aspect"][i], math.radians(prot["angle_deg"][i])
    a = w / 2 * math.sqrt(asp) / px
    b = w / 2 / math.sqrt(asp) / px
    cr, cc = prot["y_px"][i], prot["x_px"][i]
    margin = int(math.ceil(a * grow * reach)) + 3
    r0, r1 = max(int(cr) - margin, 0), min(int(cr) + margin + 1, shape[0])
    c0, c1 = max(int(cc) - margin, 0), min(int(cc) + margin + 1, shape[1])
    rr = np.arange(r0, r1)[:, None] - cr
    ccs = np.arange(c0, c1)[None, :] - cc
    u = ccs * np.cos(phi) + rr * np.sin(phi)
    v = -ccs * np.sin(phi) + rr * np.cos(phi)
    rho = np.sqrt((u / a) ** 2 + (v / b) ** 2)
    return (slice(r0, r1), slice(c0, c1)), rr, ccs, rho, a


def _own_relief(height, win, rr, ccs, rho):
    """A protrusion's own relief in its window (zero outside its footprint) and the surface
    under it: a plane fitted to the ring just outside the footprint (the weave under it is lost)."""
    h = height[win]
    ring = (rho > 1.05) & (rho < 1.6)
    design = np.column_stack([np.ones(ring.sum()), rr.repeat(ccs.shape[1], 1)[ring],
                              ccs.repeat(rr.shape[0], 0)[ring]])
    coef = np.linalg.lstsq(design, h[ring], rcond=None)[0]
    base = coef[0] + coef[1] * rr + coef[2] * ccs
    return np.where(rho < 1.0, h - base, 0.0)


def _change_surface(rng, later, prot, height, albedo, px):
    """Grow, remove and add protrusions on the world surface, in place. Returns the world table
    after the change (ids of ``prot``, then the new ones) and each row's status.

    Only lone domes, craters and mesas grow or go (a cluster's members overlap, so one member's
    own relief is not separable); one permutation of them from ``rng`` picks both, growth first."""
    n = prot["id"].size
    rad = prot["width_um"] * np.sqrt(prot["aspect"]) / 2 / px
    xy = np.column_stack([prot["x_px"], prot["y_px"]])
    tree = cKDTree(xy) if n else None
    status = np.array(["unchanged"] * n, dtype="<U9")
    after = {k: np.array(v, copy=True) for k, v in prot.items() if k != "id"}
    lone = np.flatnonzero((prot["cluster"] == 0) & np.isin(prot["shape"], ("dome", "crater", "mesa")))
    order = rng.permutation(lone)
    n_grow = int(round(later.grown_fraction * lone.size))
    n_gone = int(round(later.gone_fraction * lone.size))
    _grow_protrusions(rng, later, prot, height, albedo, px, order, n_grow, (tree, xy, rad),
                      status, after)
    for i in [j for j in order if status[j] == "unchanged"][:n_gone]:
        _remove_protrusion(prot, i, height, albedo, px)
        status[i] = "gone"
    return _erupt_domes(rng, later, height, albedo, px, (tree, xy, rad), status, after)


def _grow_protrusions(rng, later, prot, height, albedo, px, order, n_grow, near, status, after):
    """Grow up to ``n_grow`` of the protrusions ``order`` (in that order), each where its grown
    footprint stays clear of every neighbour's and of the field's edge: its own relief and colour
    redrawn ``s_w`` x wider and ``s_h`` x higher. Marks them "grown" in ``status``/``after``."""
    tree, xy, rad = near
    shape = height.shape
    grown = []
    for i in order:
        if len(grown) >= n_grow:
            break
        sw = rng.uniform(*later.width_growth)
        near_i = tree.query_ball_point(xy[i], sw * rad[i] + rad.max() + 4)
        if any(j != i and np.hypot(*(xy[j] - xy[i])) < sw * rad[i] + rad[j] + 4 for j in near_i):
            continue
        win, rr, ccs, rho, a = _ellipse(prot, i, px, shape, grow=sw)
        if rho.shape != rr.shape[:1] + ccs.shape[1:] or win[0].start == 0 or win[1].start == 0 \
                or win[0].stop == shape[0] or win[1].stop == shape[1]:
            continue
        sh = rng.uniform(*later.height_growth)
        own = _own_relief(height, win, rr, ccs, rho)
        # the relief and colour drawn again sw x wider (sampled at the shrunk coordinates)
        r_src = rr / sw + (prot["y_px"][i] - win[0].start)
        c_src = ccs / sw + (prot["x_px"][i] - win[1].start)
        rr_b, cc_b = np.broadcast_arrays(r_src, c_src)
        grown_own = ndimage.map_coordinates(own, [rr_b, cc_b], order=1, mode="constant")
        height[win] += sh * grown_own - own
        inside = rho / sw < 1.0 + 1.0 / a
        sub = albedo[win]
        for ch in range(sub.shape[2]):
            src = ndimage.map_coordinates(sub[..., ch], [rr_b, cc_b], order=1, mode="nearest")
            sub[..., ch] = np.where(inside, src, sub[..., ch])
        status[i] = "grown"
        after["width_um"][i] *= sw
        after["height_um"][i] *= sh
        grown.append(i)


def _remove_protrusion(prot, i, height, albedo, px):
    """Flatten protrusion ``i`` to the plane of the paint around it and paint its footprint the
    median colour of the ring just outside it (as a fallen-off protrusion leaves paint behind)."""
    win, rr, ccs, rho, a = _ellipse(prot, i, px, height.shape)
    height[win] -= _own_relief(height, win, rr, ccs, rho)
    sub = albedo[win]
    ring = (rho > 1.2) & (rho < 1.6)
    paint = np.median(sub[ring], axis=0)
    sub[rho < 1.0 + 1.0 / a] = paint


def _erupt_domes(rng, later, height, albedo, px, near, status, after):
    """New domes (``new_per_cm2``, widths ``new_width_um``) where there is room: off every
    protrusion and each other, inside the field (60 tries each, else dropped). Appends their
    rows to ``after`` as "new"; returns ``after`` and ``status``."""
    tree, xy, rad = near
    shape = height.shape
    area_cm2 = shape[0] * shape[1] * px * px / _UM2_PER_CM2
    n_new = int(rng.poisson(later.new_per_cm2 * area_cm2)) if later.new_per_cm2 > 0 else 0
    colour = np.array(PROTRUSION_COLOUR)[: albedo.shape[2]]
    new_rows = []
    for w_um in _protrusion_widths(rng, n_new, later.new_width_um) if n_new else []:
        r = w_um / 2 / px
        for _ in range(60):
            cr, cc = rng.uniform(r + 8, shape[0] - r - 8), rng.uniform(r + 8, shape[1] - r - 8)
            if tree is not None and np.any(np.hypot(*(xy - (cc, cr)).T) < r + rad + 6):
                continue
            if any(np.hypot(cc - x, cr - y) < r + rn + 6 for x, y, rn in new_rows):
                continue
            break
        else:
            continue
        h_dome = rng.uniform(0.15, 0.35) * w_um
        gamma = rng.uniform(1.0, 1.6)
        m_ = int(math.ceil(r)) + 2
        win = (slice(int(cr) - m_, int(cr) + m_ + 1), slice(int(cc) - m_, int(cc) + m_ + 1))
        rr = np.arange(win[0].start, win[0].stop)[:, None] - cr
        ccs = np.arange(win[1].start, win[1].stop)[None, :] - cc
        rho = np.sqrt(rr ** 2 + ccs ** 2) / r
        height[win] += h_dome * _dome_profile(rho, gamma, None)
        wgt = np.clip((1 - rho) * r, 0, 1)[..., None]
        albedo[win] = albedo[win] * (1 - wgt) + colour * rng.uniform(0.92, 1.05) * wgt
        new_rows.append((cc, cr, r))
        new_row = {"x_px": cc, "y_px": cr, "width_um": w_um, "height_um": h_dome, "aspect": 1.0,
                   "angle_deg": 0.0, "shape": "dome", "crater": False, "weak": False, "dark": False,
                   "cluster": 0, "region": 0}
        for key in after:
            after[key] = np.append(after[key], np.asarray(new_row[key], dtype=after[key].dtype))
        status = np.append(status, "new")
    return after, status


def _view_table(world, status, keep, to_view, shape, region_of):
    """The protrusion table of one view: world rows ``keep`` whose centre lands in the field."""
    world_xy = np.column_stack([world["x_px"], world["y_px"]])
    xy = to_view(world_xy)
    m, n = shape
    inside = keep & (xy[:, 0] >= 0) & (xy[:, 0] <= n - 1) & (xy[:, 1] >= 0) & (xy[:, 1] <= m - 1)
    idx = np.flatnonzero(inside)
    order = idx[np.lexsort((xy[idx, 0], xy[idx, 1]))]
    table = {"id": np.arange(1, order.size + 1, dtype=np.int32)}
    table.update({k: v[order] for k, v in world.items()})
    table.update({"x_px": xy[order, 0], "y_px": xy[order, 1], "status": status[order],
                  "region": region_of(world_xy[order]).astype(np.int32)})
    ids = np.zeros(len(status), np.int32)
    ids[order] = table["id"]
    return table, ids, xy


def _render_view(height, albedo, regions, spec, px, rng, world_like):
    """A capture of ``height``/``albedo`` (already in the view's pixel grid) under lamps from ``rng``."""
    height = (height - np.median(height)).astype(np.float32)
    albedo = albedo.astype(np.float32)
    normals = normals_from_height(height, pixel_size_um=px)
    positions = light_positions(rng, n_lights=spec.n_lights, elevation_deg=spec.elevation_deg,
                                distance_mm=spec.distance_mm, azimuth_jitter=spec.azimuth_jitter)
    intensities = 1 + rng.uniform(-spec.intensity_jitter, spec.intensity_jitter, spec.n_lights)
    nz = Nuisances()
    # the spec's lamp and lens nuisances (black level, vignetting, beams; none by default), the
    # same camera and lamp models at both dates
    _lamp_and_lens_nuisances(spec, nz, positions, intensities, height.shape)
    amax = albedo if albedo.ndim == 2 else albedo.max(axis=2)
    peak = _peak(_shading(normals, height, px, positions, None, intensities, beam_axes=nz.beam_axes,
                          beam_exponent=nz.beam_exponent), amax, nz)
    exposure = spec.exposure_fraction * 65535.0 / peak
    gain = 65535.0 / spec.full_well_e
    images = render_images(height, albedo, pixel_size_um=px, light_positions_mm=positions,
                           intensities=intensities, rng=rng, noise=spec.noise, gain=gain,
                           read_noise=spec.read_noise, exposure=exposure, dtype=np.uint16,
                           nuisances=nz)
    view_spec = dataclasses.replace(spec, pixel_size_um=px)
    return SyntheticCapture(images=images, light_positions_mm=positions, intensities=intensities,
                            height_um=height, normals=normals, albedo=albedo, regions=regions,
                            region_names=world_like.region_names,
                            region_light=world_like.region_light, protrusions={}, spec=view_spec,
                            exposure=float(exposure), gain=float(gain), nuisances=nz)


def make_capture_pair(spec: Optional[SyntheticSpec] = None, later: Optional[LaterSpec] = None, *,
                      progress: Progress = None, **overrides) -> CapturePair:
    """Two captures of one painted surface, years apart: A, and B from another camera pose
    under other lamps after some protrusions grew, erupted or went.

    Parameters
    ----------
    spec : SyntheticSpec, optional
        The scene and camera of A (its ``shape`` and ``pixel_size_um``). Of the nuisances of a
        real capture, the canvas bow (``bow_um``), black level, vignetting and lamp beams are
        drawn (the same camera and lamp models at both dates, the lamps placed again); stray
        light, cast shadows and cracks are not.
    later : LaterSpec, optional
        How B differs (default :class:`LaterSpec()`; :meth:`LaterSpec.unchanged` for the
        repeatability pair).
    **overrides
        Fields of :class:`SyntheticSpec`.

    Returns
    -------
    CapturePair
        ``a``, ``b`` (:class:`SyntheticCapture`; ``protrusions`` of each view: the columns of
        :func:`make_capture`'s in the view's pixels, plus ``status``), ``b_to_a``, ``changes``
        (the truth, one row per protrusion of either field) and ``info`` (shift, rotation, scale,
        counts).

    Notes
    -----
    One world surface (:func:`make_capture`'s scene on a field wide enough for both views) is
    seen by A as a crop and by B through the similarity (cubic interpolation of the height,
    linear of the albedo, nearest of the colour areas); the changes are made on the world
    between the two renders: a grown protrusion's own relief (the height above a plane fitted
    around it) is redrawn ``s_w`` x wider and ``s_h`` x higher, a gone one's is removed and its
    colour set to the paint's around it. Cost: about 2x :func:`make_capture` of the same shape.

    Examples
    --------
    >>> pair = make_capture_pair(shape=(120, 160), n_lights=4, protrusion_density_light=0,
    ...                          protrusion_density_dark=0, later=LaterSpec(shift_px=(10.0, 0.0),
    ...                          rotation_deg=0.0, scale=1.0))
    >>> pair.b_to_a[:2, 2].tolist(), pair.b.images.shape
    ([10.0, 0.0], (4, 120, 160, 3))
    """
    spec = dataclasses.replace(spec or SyntheticSpec(), **_checked_overrides(overrides))
    spec.shape = tuple(int(s) for s in spec.shape)
    later = later or LaterSpec()
    rng = np.random.default_rng((int(later.seed), zlib.crc32(b"later capture")))
    m, n = spec.shape
    px = float(spec.pixel_size_um)
    shift, rot, scale = _later_pose(rng, later)
    b_to_a = similarity_matrix((m, n), shift_px=shift, rotation_deg=rot, scale=scale)
    margin = _world_margin(b_to_a, later, (m, n))
    report(progress, 0.0, "the surface")
    world = make_capture(spec, shape=(m + 2 * margin, n + 2 * margin), n_lights=3, noise=False)
    height, albedo = world.height_um.astype(np.float64), world.albedo.astype(np.float64)
    if albedo.ndim == 2:
        albedo = albedo[..., None]
    region_w = world.regions
    crop = (slice(margin, margin + m), slice(margin, margin + n))
    alb_a = albedo[crop] if world.albedo.ndim == 3 else albedo[crop][..., 0]
    report(progress, 0.3, "capture A")
    a = _render_view(height[crop], alb_a, region_w[crop], spec, px,
                     np.random.default_rng((int(spec.seed), zlib.crc32(b"view a"))), world)
    report(progress, 0.5, "the changes")
    after, status = _change_surface(rng, later, world.protrusions, height, albedo, px)
    h_b, alb_b, reg_b = _b_grid(height, albedo, region_w, b_to_a, margin, (m, n),
                                grey=world.albedo.ndim == 2)
    report(progress, 0.7, "capture B")
    b = _render_view(h_b, alb_b, reg_b, spec, px * scale,
                     np.random.default_rng((int(later.seed), zlib.crc32(b"view b"))), world)
    changes = _pair_tables(a, b, world, after, status, b_to_a, margin)
    counts = {s: int(np.sum(changes["status"] == s)) for s in ("unchanged", "grown", "new", "gone")}
    info = {"shift_px": list(shift), "rotation_deg": rot, "scale": scale, "margin_px": margin,
            "pixel_size_um_a": px, "pixel_size_um_b": px * scale, "counts": counts}
    logger.info("capture pair: shift %s px, rotation %.2f deg, scale %.4f; %s", shift, rot, scale, counts)
    report(progress, 1.0, "done")
    return CapturePair(a, b, b_to_a, changes, later, info)


def _later_pose(rng, later):
    """B's pose against A: shift (px), rotation (deg) and scale, each the given value or drawn
    within its bound (the shift at least half ``max_shift_px``, in a random direction)."""
    if later.shift_px is None:
        ang, mag = rng.uniform(0, 2 * np.pi), rng.uniform(0.5, 1.0) * later.max_shift_px
        shift = (mag * math.cos(ang), mag * math.sin(ang))
    else:
        shift = tuple(float(s) for s in later.shift_px)
    rot = (rng.uniform(-1, 1) * later.max_rotation_deg if later.rotation_deg is None
           else float(later.rotation_deg))
    scale = (1 + rng.uniform(-1, 1) * later.max_scale_change if later.scale is None
             else float(later.scale))
    return shift, rot, scale


def _world_margin(b_to_a, later, shape):
    """The margin (px) around A's field that the world surface needs: wide enough for both
    fields, and for any pose within the bounds (so that A is the same capture for every later
    capture of one spec: one A, several B)."""
    m, n = shape
    corners = np.array([[0, 0, 1], [n - 1, 0, 1], [0, m - 1, 1], [n - 1, m - 1, 1]], float)
    reach = (b_to_a @ corners.T)[:2]
    bound = (later.max_shift_px + math.hypot(m, n) / 2
             * (math.radians(later.max_rotation_deg) + later.max_scale_change))
    return int(math.ceil(max(bound, -reach.min(), reach[0].max() - (n - 1),
                             reach[1].max() - (m - 1)))) + 8


def _b_grid(height, albedo, region_w, b_to_a, margin, shape, *, grey):
    """The changed world seen in B's pixel grid (world = A + margin = b_to_a (x_b) + margin):
    height by cubic interpolation, albedo by linear, colour areas by nearest."""
    m, n = shape
    yy, xx = np.mgrid[0:m, 0:n].astype(np.float64)
    wx = b_to_a[0, 0] * xx + b_to_a[0, 1] * yy + b_to_a[0, 2] + margin
    wy = b_to_a[1, 0] * xx + b_to_a[1, 1] * yy + b_to_a[1, 2] + margin
    h_b = ndimage.map_coordinates(height, [wy, wx], order=3, mode="nearest")
    alb_b = np.stack([ndimage.map_coordinates(albedo[..., c], [wy, wx], order=1, mode="nearest")
                      for c in range(albedo.shape[2])], axis=-1)
    if grey:
        alb_b = alb_b[..., 0]
    reg_b = ndimage.map_coordinates(region_w, [wy, wx], order=0, mode="nearest").astype(region_w.dtype)
    return h_b, alb_b, reg_b


def _pair_tables(a, b, world, after, status, b_to_a, margin):
    """Fill ``a.protrusions`` and ``b.protrusions`` (each view's rows in its pixels) and return
    the truth of the changes: one row per protrusion in either field, with its ids, positions,
    status and widths and heights at both dates (NaN where absent)."""
    m, n = a.images.shape[1:3]
    region_w = world.regions
    a_to_b = np.linalg.inv(b_to_a)
    n_before = world.protrusions["id"].size

    def region_of(xy_world):
        r = np.clip(np.rint(xy_world[:, 1]).astype(int), 0, region_w.shape[0] - 1)
        c = np.clip(np.rint(xy_world[:, 0]).astype(int), 0, region_w.shape[1] - 1)
        return region_w[r, c]

    def to_a(xy):
        return xy - margin

    def to_b(xy):
        h = np.column_stack([xy - margin, np.ones(len(xy))]) @ a_to_b.T
        return h[:, :2]

    present_a = np.arange(len(status)) < n_before
    present_b = status != "gone"
    world_a = {k: np.concatenate([world.protrusions[k], after[k][n_before:]]) for k in after}
    a.protrusions, ids_a, xy_a = _view_table(world_a, status, present_a, to_a, (m, n), region_of)
    b.protrusions, ids_b, xy_b = _view_table(after, status, present_b, to_b, (m, n), region_of)
    rows = np.flatnonzero((ids_a > 0) | (ids_b > 0))
    nan = np.full(len(status), np.nan)
    return {"id_a": ids_a[rows], "id_b": ids_b[rows],
            "x_px_a": xy_a[rows, 0], "y_px_a": xy_a[rows, 1],
            "x_px_b": xy_b[rows, 0], "y_px_b": xy_b[rows, 1], "status": status[rows],
            "width_um_a": np.where(present_a, world_a["width_um"], nan)[rows],
            "width_um_b": np.where(present_b, after["width_um"], nan)[rows],
            "height_um_a": np.where(present_a, world_a["height_um"], nan)[rows],
            "height_um_b": np.where(present_b, after["height_um"], nan)[rows]}
