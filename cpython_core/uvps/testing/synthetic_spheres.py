"""Synthetic calibration captures of spheres under the lamps of a synthetic painting capture.

A sphere capture is what a conservator takes before (or after) the painting: one or more spheres in
the field, photographed once under every lamp position of the painting capture. Matte white spheres
show the lamp's direction in their shading; glossy black spheres in the mirror highlight. The
spheres here have known centres and radii, so :mod:`uvps.core.spheres` and ``uvps calibrate`` are scored
against the lamps that rendered them.

Frames follow ``docs/architecture.md`` (x right, y up, z toward the camera; mm from the image
centre). Each sphere rests on the plane of the painting (z = 0): its centre is one radius above it.
The camera is orthographic (viewer +z), as for the painting capture, or a pinhole ``camera_distance_mm``
above the image centre: each pixel then sees where the ray from the camera's centre through its point on
the painting's plane first meets a sphere (the sphere's outline a slight ellipse), and the highlight
reflects the view vector of that point.

Image model (counts, ``c`` the exposure)::

    I_k = c * V * E_k * (|L_k| / |L_k - P|)^2 * beam_k(P) * [albedo * max(0, n . l) + spec(n . h)]
          + flare + noise + black

``P`` the surface point, ``n`` its normal, ``l = (L_k - P) / |L_k - P|``, ``h`` the half vector of
``l`` and the view direction; ``spec`` a Gaussian lobe in the angle between ``n`` and ``h`` (a
glossy sphere's highlight, saturating the sensor; a mirror sphere's is flat out to
:data:`MIRROR_FLAT_DEG`, the lamp's own image, with a sharp edge), ``flare`` a star of thin spikes around a
saturated highlight (lens flare), ``V`` the vignetting. Lamps, beams, vignetting, black level and
noise are the painting capture's (:class:`uvps.testing.synthetic.SyntheticCapture`). The background is the
painting's albedo, seen flat, so that detection meets a textured field. An optional stand (a dark
post in front of the lower part of each sphere) hides part of the disc.
"""
from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from ..errors import UVPSInputError
from ..files.outputs import atomic_output_dir
from .synthetic_files import _write_camera_tiff
from .synthetic_render import _add_noise, _substream, pixel_centres_mm
from .synthetic_spec import LUMINANCE, SyntheticCapture

__all__ = ["SphereSpec", "SphereCapture", "make_sphere_capture", "write_sphere_capture", "DEFAULT_SPHERES"]

#: Angular spread (deg) of a glossy sphere's highlight: the lamp's angular size and the polish.
GLOSS_SPREAD_DEG = 1.5
#: A mirror (chrome) sphere shows the lamp's own image: flat out to this angle between the normal and
#: the half vector (half the lamp's angular radius: a 40 mm lamp at 500 mm), then a Gaussian edge of
#: :data:`MIRROR_EDGE_DEG` (the polish and the lens).
MIRROR_FLAT_DEG = 1.15
MIRROR_EDGE_DEG = 0.2
#: A sphere's limb reflecting the lit ground (``make_sphere_capture(limb_reflection=...)``): the disc's
#: pixels whose normal is within this ``n_z`` of the view's perpendicular (a band 4.6 % of the radius
#: wide, 3.7 px on an 80 px sphere) over the lower arc of this many degrees of its rim.
LIMB_BAND_NZ = 0.3
LIMB_ARC_DEG = 120.0
#: Albedo of each kind's diffuse part: a white matte sphere, a black glossy one, a chrome one.
ALBEDO = {"matte": 0.9, "glossy": 0.02, "mirror": 0.005}


@dataclass(frozen=True)
class SphereSpec:
    """One sphere: ``kind`` "matte", "glossy" or "mirror", its centre as fractions of the frame's width and
    height (``(0, 0)`` the top left corner), and its radius in mm."""

    kind: str
    centre: tuple
    radius_mm: float


#: Two glossy spheres in opposite corners (RTI practice: two or more give the lamps' 3-D positions).
DEFAULT_SPHERES = (SphereSpec("glossy", (0.13, 0.17), 2.5), SphereSpec("glossy", (0.87, 0.83), 2.5))


@dataclass
class SphereCapture:
    """A rendered sphere capture and its truth.

    ``spheres``: one dict per sphere with ``centre_px`` [col, row], ``radius_px``, ``kind`` and
    ``centre_mm`` [x, y, z]; ``light_positions_mm`` (K, 3) the painting capture's lamps; ``dark`` the
    frame with the lamps off at the sphere capture's exposure (its own: the painting's is at another).
    """

    images: np.ndarray
    light_positions_mm: np.ndarray
    spheres: list
    pixel_size_um: float
    files: list = field(default_factory=list)
    #: The frame with the lamps off at the sphere capture's exposure (black level and the room's stray
    #: light), when the painting capture has either; None otherwise.
    dark: Optional[np.ndarray] = None


def make_sphere_capture(capture: SyntheticCapture, spheres: Sequence[SphereSpec] = DEFAULT_SPHERES, *,
                        stand: bool = False, stand_top: float = 0.55, stand_half_width: float = 0.35,
                        flare: bool = True, seed: Optional[int] = None,
                        gloss_deg: float = GLOSS_SPREAD_DEG, specular: float = 20.0,
                        exposure: float = 0.5, camera_distance_mm: Optional[float] = None,
                        limb_reflection: float = 0.0) -> SphereCapture:
    """Render the spheres under the lamps of ``capture`` (uint16; RGB when the capture is).

    Parameters
    ----------
    capture : SyntheticCapture
        The painting capture whose lamps (positions, ``E_k``, beams), vignetting, black level, noise
        and exposure the sphere capture shares.
    spheres : sequence of SphereSpec
        The spheres (:data:`DEFAULT_SPHERES`: two glossy ones in opposite corners).
    stand : bool
        A dark post in front of the lower part of each sphere (hides about a fifth of the disc).
    stand_top, stand_half_width : float
        The post's top below the sphere's centre and its half width, in radii (0.33 and 1.2: a
        holder hiding the lower third of the disc across its width).
    flare : bool
        A star of thin spikes around each saturated highlight.
    seed : int, optional
        Noise stream (default: the capture's seed).
    gloss_deg : float
        Angular spread of the glossy highlight.
    specular : float
        The highlight's peak relative to a white matte surface facing the lamp (saturates).
    exposure : float
        The exposure relative to the painting capture's (a white sphere facing a lamp is brighter
        than the painting; at 0.5 part of a matte sphere still saturates under the lowest lamps).
    camera_distance_mm : float, optional
        A pinhole camera this far above the image centre (mm); None: orthographic. The spheres' truth
        ``centre_px`` and ``radius_px`` are then their outline's centre and mean radius (from the
        pixels they cover), ``centre_mm`` the sphere's own centre.

    Returns
    -------
    SphereCapture

    Examples
    --------
    >>> from uvps.testing.synthetic import make_capture
    >>> cap = make_capture(shape=(120, 160), n_lights=4, seed=1, rgb=False)
    >>> sc = make_sphere_capture(cap, [SphereSpec("matte", (0.5, 0.5), 0.5)])
    >>> sc.images.shape, sc.images.dtype, round(sc.spheres[0]["radius_px"], 1)
    ((4, 120, 160), dtype('uint16'), 33.3)
    """
    spec = capture.spec
    px = float(spec.pixel_size_um)
    for s in spheres:
        if s.kind not in ALBEDO or not s.radius_mm > 0:
            raise UVPSInputError(f"sphere {s}: kind must be 'matte', 'glossy' or 'mirror' and radius_mm > 0")
    if camera_distance_mm is not None and not (math.isfinite(camera_distance_mm)
                                               and camera_distance_mm > 2 * max(s.radius_mm for s in spheres)):
        raise UVPSInputError(f"camera_distance_mm must be above the spheres; got {camera_distance_mm!r}")
    scene = _SphereScene.of_capture(capture, gloss_deg)
    scene.camera_mm = camera_distance_mm
    scene.limb_reflection = float(limb_reflection)
    truth = [scene.add_sphere(s, stand=stand, stand_top=stand_top, stand_half_width=stand_half_width)
             for s in spheres]
    rng = np.random.default_rng(_substream(spec.seed if seed is None else seed, "spheres").integers(2 ** 32))
    out, stray, black = _render_sphere_images(capture, scene, rng, flare=flare, specular=specular,
                                              exposure=exposure)
    lamps = capture.light_positions_mm
    files = [f"sphere_{k:02d}.tif" for k in range(len(lamps))]
    dark = _sphere_dark_frame(capture, stray, black, rng)
    return SphereCapture(out, np.asarray(lamps, float), truth, px, files, dark)


@dataclass
class _SphereScene:
    """What each pixel of a sphere capture sees: the background (the painting seen flat, and the
    stands) as points ``P``, normals ``N`` and grey ``albedo``; over it the spheres, with the
    fraction of each pixel's area they ``cover`` (a camera integrates over the pixel; sampling the
    rim at pixel centres alone makes it jagged, which moves a fitted circle by up to 0.02 px with
    the centre's sub-pixel phase), their normals, points, albedo, specular weight, the highlight's
    angular spread and its flat top (a mirror's lamp image)."""

    X: np.ndarray
    Y: np.ndarray
    px_mm: float
    P: np.ndarray
    N: np.ndarray
    albedo: np.ndarray
    cover: np.ndarray
    sN: np.ndarray
    sP: np.ndarray
    s_alb: np.ndarray
    spec_w: np.ndarray
    spread: np.ndarray
    flat: np.ndarray
    #: the pinhole camera's height above the image centre (mm); None: orthographic
    camera_mm: Optional[float] = None
    #: albedo of the lit ground a glossy or mirror sphere's lower limb reflects (0: none)
    limb_reflection: float = 0.0

    @classmethod
    def of_capture(cls, capture: SyntheticCapture, gloss_deg: float) -> "_SphereScene":
        """The painting of ``capture`` seen flat (grey: its luminance), no sphere yet."""
        m, n = capture.images.shape[1:3]
        px = float(capture.spec.pixel_size_um)
        x, y = pixel_centres_mm((m, n), px)
        X = np.broadcast_to(x, (m, n))
        Y = np.broadcast_to(y, (m, n))
        P = np.stack([X, Y, np.zeros((m, n))], axis=-1)            # surface points (mm)
        N = np.zeros((m, n, 3))
        N[..., 2] = 1.0
        alb = capture.albedo if capture.albedo.ndim == 2 else capture.albedo @ LUMINANCE
        albedo = np.asarray(alb, np.float64).copy()
        return cls(X, Y, px / 1000.0, P, N, albedo, np.zeros((m, n)), np.zeros((m, n, 3)),
                   np.zeros((m, n, 3)), np.zeros((m, n)), np.zeros((m, n)),
                   np.full((m, n), math.radians(gloss_deg)), np.zeros((m, n)))

    def add_sphere(self, s: SphereSpec, *, stand, stand_top, stand_half_width) -> dict:
        """Put sphere ``s`` (and its stand) into the scene; returns its truth (kind, centre and
        radius in pixels, centre in mm)."""
        X, Y, px_mm = self.X, self.Y, self.px_mm
        m, n = X.shape
        c0 = s.centre[0] * (n - 1)
        r0 = s.centre[1] * (m - 1)
        R = s.radius_mm
        rpx = R / px_mm
        cx, cy = (c0 - (n - 1) / 2.0) * px_mm, ((m - 1) / 2.0 - r0) * px_mm
        if self.camera_mm is not None:
            return self._add_sphere_seen(s, (cx, cy), stand=stand, stand_top=stand_top,
                                         stand_half_width=stand_half_width)
        dx, dy = (X - cx) / R, (Y - cy) / R
        rho = np.sqrt(dx * dx + dy * dy)
        frac = _coverage((X - cx) / px_mm, (Y - cy) / px_mm, rpx)
        on = frac > 0
        # a rim pixel shows the sphere just inside its outline
        scale = np.minimum(1.0, (1.0 - 0.5 / rpx) / np.maximum(rho, 1e-12))
        dx, dy = dx * scale, dy * scale
        nz = np.sqrt(np.clip(1.0 - dx * dx - dy * dy, 0.0, None))
        self.cover[on] = frac[on]
        self.sN[on] = np.stack([dx, dy, nz], axis=-1)[on]
        self.sP[on] = np.stack([cx + R * dx, cy + R * dy, R + R * nz], axis=-1)[on]
        self._kind_and_stand(s, on, (cx, cy), stand=stand, stand_top=stand_top, stand_half_width=stand_half_width)
        return {"kind": s.kind, "centre_px": [float(c0), float(r0)], "radius_px": float(rpx),
                "centre_mm": [float(cx), float(cy), float(R)]}

    def _kind_and_stand(self, s: SphereSpec, on, centre_xy, *, stand, stand_top, stand_half_width):
        """The sphere's albedo and highlight on the pixels it covers (``on``), and its stand."""
        X, Y = self.X, self.Y
        m, n = X.shape
        cx, cy = centre_xy
        R = s.radius_mm
        self.s_alb[on] = ALBEDO[s.kind]
        if s.kind != "matte":
            self.spec_w[on] = 1.0
        if s.kind == "mirror":
            self.spread[on] = math.radians(MIRROR_EDGE_DEG)
            self.flat[on] = math.radians(MIRROR_FLAT_DEG)
        if s.kind != "matte" and self.limb_reflection > 0:
            # the lower limb's grazing normals see the lit ground: shaded as the ground (normal +z)
            nrm = self.sN
            band = on & (nrm[..., 2] < LIMB_BAND_NZ) & (nrm[..., 1] < -math.cos(math.radians(LIMB_ARC_DEG / 2)))
            self.s_alb[band] = self.limb_reflection
            self.spec_w[band] = 0.0
            self.sN[band] = (0.0, 0.0, 1.0)
        if stand:
            post = (np.abs(X - cx) < stand_half_width * R) & (Y < cy - stand_top * R)
            self.cover[post] = 0.0
            self.P[post] = np.stack([X, Y, np.full((m, n), R)], axis=-1)[post]
            self.albedo[post] = 0.04

    def _add_sphere_seen(self, s: SphereSpec, centre_xy, *, stand, stand_top, stand_half_width) -> dict:
        """:meth:`add_sphere` under the pinhole camera at ``camera_mm``: each pixel's ray from the camera's
        centre through its point on the plane, met by the sphere where ``t^2 - 2 b t + c = 0`` has a root
        (``b = w . (S - C)``, ``c = |S - C|^2 - R^2``, ``w`` the ray's unit direction); the cover from an
        8 x 8 grid of rays across each pixel near the outline."""
        X, Y, px_mm = self.X, self.Y, self.px_mm
        m, n = X.shape
        R = s.radius_mm
        S = np.array([centre_xy[0], centre_xy[1], R])
        C = np.array([0.0, 0.0, float(self.camera_mm)])

        def rays(x, y):
            x, y = np.broadcast_arrays(x, y)
            w = np.stack([x, y, np.zeros(x.shape)], axis=-1) - C
            w /= np.linalg.norm(w, axis=-1, keepdims=True)
            b = w @ (S - C)
            miss = np.cross(w, S - C)
            return w, b, np.einsum("...i,...i->...", miss, miss)     # the ray's squared miss of S
        w, b, miss2 = rays(X, Y)
        frac = (miss2 < R * R).astype(np.float64)
        rim = np.abs(np.sqrt(miss2) - R) < 1.5 * px_mm
        o = ((np.arange(8) + 0.5) / 8 - 0.5) * px_mm
        sub = rays(X[rim][:, None, None] + o[None, None, :], Y[rim][:, None, None] + o[None, :, None])[2]
        frac[rim] = (sub < R * R).mean(axis=(1, 2))
        on = frac > 0
        # a rim pixel shows the sphere just inside its outline
        d = np.sqrt(miss2)
        d_in = np.minimum(d, R * (1.0 - 0.5 * px_mm / R))
        q = (C + b[..., None] * w - S) * (d_in / np.maximum(d, 1e-12))[..., None]
        hit = S + q - np.sqrt(R * R - d_in * d_in)[..., None] * w
        self.cover[on] = frac[on]
        self.sN[on] = ((hit - S) / R)[on]
        self.sP[on] = hit[on]
        tot = frac.sum()
        truth = {"kind": s.kind, "centre_px": [float((frac * np.arange(n)[None, :]).sum() / tot),
                                               float((frac * np.arange(m)[:, None]).sum() / tot)],
                 "radius_px": float(math.sqrt(tot / math.pi)), "centre_mm": [float(v) for v in S]}
        self._kind_and_stand(s, on, centre_xy, stand=stand, stand_top=stand_top, stand_half_width=stand_half_width)
        return truth


def _render_sphere_images(capture, scene: _SphereScene, rng, *, flare, specular, exposure):
    """Render one uint16 picture per lamp of ``capture``: background and spheres blended by their
    cover, the capture's vignetting, flare around the glossy highlights, the room's stray light,
    noise and black level (the draws of ``rng`` lamp by lamp). Returns the stack, the stray light
    (None when the capture has none) and the black level per channel."""
    spec = capture.spec
    m, n = scene.cover.shape
    idx = np.flatnonzero(scene.cover > 0)
    cover_s, sN, sP = scene.cover.ravel()[idx], scene.sN.reshape(-1, 3)[idx], scene.sP.reshape(-1, 3)[idx]
    s_alb, spec_s = scene.s_alb.ravel()[idx], scene.spec_w.ravel()[idx]
    s2 = 2.0 * scene.spread.ravel()[idx] ** 2
    a0 = scene.flat.ravel()[idx]
    glossy = np.zeros(m * n)
    glossy[idx] = spec_s * (cover_s >= 0.5)
    glossy = glossy.reshape(m, n)
    view = None
    if scene.camera_mm is not None:         # each surface point's own view vector
        view = np.array([0.0, 0.0, scene.camera_mm]) - sP
        view /= np.linalg.norm(view, axis=-1, keepdims=True)
    nzs = capture.nuisances
    lamps = capture.light_positions_mm
    E = capture.intensities
    vig = nzs.vignetting if nzs.vignetting is not None and nzs.vignetting.shape == (m, n) else None
    beam = nzs.beam_axes is not None and nzs.beam_exponent > 0
    rgb = capture.images.ndim == 4
    black = (np.zeros(3 if rgb else 1, np.float32) if nzs.black_level is None
             else np.asarray(nzs.black_level, np.float32))
    # the room's stray light, in every picture at this capture's exposure (its dark frame holds it too)
    stray = None
    if nzs.stray_light is not None:
        st = np.asarray(nzs.stray_light, np.float32)
        stray = (exposure * capture.exposure * (st.mean(axis=-1) if st.ndim == 3 else st)).astype(np.float32)
    out = np.empty((len(lamps), m, n) + ((3,) if rgb else ()), np.uint16)
    for k, (L, e) in enumerate(zip(lamps, E)):
        ax = nzs.beam_axes[k] if beam else None
        sig = _radiance(L, e, scene.P.reshape(-1, 3), scene.N.reshape(-1, 3), scene.albedo.ravel(), None,
                        ax, nzs.beam_exponent, specular, s2)
        on_s = _radiance(L, e, sP, sN, s_alb, spec_s, ax, nzs.beam_exponent, specular, s2, a0, view=view)
        sig[idx] = cover_s * on_s + (1.0 - cover_s) * sig[idx]
        sig = sig.reshape(m, n)
        if vig is not None:
            sig = sig * vig
        counts = (exposure * capture.exposure * sig).astype(np.float32)
        if flare:
            counts += _flare(counts, glossy, rng)
        if stray is not None:
            counts += stray
        if rgb:     # a neutral white sphere and background, seen by the capture's colour camera
            counts = np.repeat(counts[..., None], 3, axis=2)
        if spec.noise:
            counts = _add_noise(counts, rng, gain=capture.gain, read_noise=spec.read_noise)
        counts += black if rgb else black[0]
        out[k] = np.clip(np.rint(counts), 0, 65535)
    return out, stray, black


def _sphere_dark_frame(capture, stray, black, rng):
    """The sphere capture's dark frame (lamps off: stray light, noise, black level), or None when
    the capture has neither a black level nor stray light to remove."""
    spec, nzs = capture.spec, capture.nuisances
    if nzs.black_level is None and stray is None:
        return None
    m, n = capture.images.shape[1:3]
    rgb = capture.images.ndim == 4
    counts = np.zeros((m, n), np.float32) if stray is None else stray.copy()
    if rgb:
        counts = np.repeat(counts[..., None], 3, axis=2)
    if spec.noise:
        counts = _add_noise(counts, rng, gain=capture.gain, read_noise=spec.read_noise)
    return np.clip(np.rint(counts + (black if rgb else black[0])), 0, 65535).astype(np.uint16)


def _coverage(u, v, radius_px, *, sub=8):
    """The fraction of each pixel's area inside a disc of ``radius_px`` pixels, ``(u, v)`` each pixel
    centre's offset from the disc's centre in pixels: 1 or 0 away from the rim, on it the fraction of a
    ``sub`` x ``sub`` grid of samples across the pixel that falls inside."""
    r = np.sqrt(u * u + v * v)
    frac = (r < radius_px).astype(np.float64)
    rim = np.abs(r - radius_px) < 0.75
    o = (np.arange(sub) + 0.5) / sub - 0.5
    su = u[rim][:, None, None] + o[None, None, :]
    sv = v[rim][:, None, None] + o[None, :, None]
    frac[rim] = (su * su + sv * sv < radius_px * radius_px).mean(axis=(1, 2))
    return frac


def _radiance(L, e, P, N, albedo, spec_w, beam_axis, beam_exponent, specular, s2, flat=0.0, view=None):
    """``E * (|L| / |L - P|)^2 * beam * [albedo max(0, n . l) + spec]`` at points ``P`` (n, 3) with
    normals ``N`` (n, 3): the module's image model before vignetting, exposure and noise. ``view`` (n, 3):
    each point's unit vector toward the camera (None: +z)."""
    V = L - P
    d = np.linalg.norm(V, axis=-1)
    lv = V / d[..., None]
    irr = e * float(L @ L) / (d * d)
    if beam_axis is not None:
        irr = irr * np.maximum(-(lv @ beam_axis), 0.0) ** beam_exponent
    ndl = np.einsum("...i,...i->...", N, lv)
    shade = albedo * np.maximum(ndl, 0.0)
    if spec_w is not None:
        h = lv + (np.array([0.0, 0.0, 1.0]) if view is None else view)
        h /= np.linalg.norm(h, axis=-1, keepdims=True)
        ang = np.arccos(np.clip(np.einsum("...i,...i->...", N, h), -1.0, 1.0))
        off = np.maximum(ang - flat, 0.0)
        shade = shade + specular * spec_w * np.exp(-off * off / s2) * (ndl > 0)
    return irr * shade


def _flare(counts, glossy, rng, *, full=65535.0):
    """A star of thin spikes (6, random rotation) around the brightest saturated highlight of each
    glossy sphere in one image (lens flare); none when nothing saturates."""
    add = np.zeros_like(counts)
    sat = (counts >= full) & (glossy > 0)
    if not sat.any():
        return add
    from scipy import ndimage

    lab, n_lab = ndimage.label(sat)
    m, n = counts.shape
    for i in range(1, n_lab + 1):
        r0, c0 = ndimage.center_of_mass(sat, lab, i)
        size = math.sqrt((lab == i).sum())
        length = 3.0 * size + 15.0
        reach = int(4 * length)          # the spikes fade to 2 % of their start beyond 4 lengths
        ra, rb = max(0, int(r0) - reach), min(m, int(r0) + reach + 1)
        ca, cb = max(0, int(c0) - reach), min(n, int(c0) + reach + 1)
        rr, cc = np.mgrid[ra:rb, ca:cb]
        box = add[ra:rb, ca:cb]
        rot = rng.uniform(0, np.pi / 3)
        for j in range(6):
            t = rot + j * np.pi / 3
            u = (cc - c0) * math.cos(t) - (rr - r0) * math.sin(t)      # along the spike
            v = (cc - c0) * math.sin(t) + (rr - r0) * math.cos(t)      # across it
            on = (u > 0) & (np.abs(v) < 4.0)
            box[on] += (0.6 * full * np.exp(-u[on] / length) * np.exp(-0.5 * (v[on] / 0.8) ** 2)).astype(np.float32)
    return add


def write_sphere_capture(sc: SphereCapture, folder, *, truth: bool = True) -> list:
    """Write a sphere capture as ``sphere_NN.tif`` (16-bit, calibrated in um), its ``dark/dark.tif`` when it
    has one, with
    ``truth/spheres.csv`` (``col,row,radius_px,kind``: a ``--sphere-circles`` file) and
    ``truth/lights_positions_mm.csv`` when ``truth``. Returns the paths written."""
    folder = Path(folder)
    written = []
    with atomic_output_dir(folder) as tmp:
        for name, img in zip(sc.files, sc.images):
            _write_camera_tiff(tmp / name, img, sc.pixel_size_um)
            written.append(name)
        if sc.dark is not None:
            (tmp / "dark").mkdir()
            _write_camera_tiff(tmp / "dark" / "dark.tif", sc.dark, sc.pixel_size_um)
            written.append("dark/dark.tif")
        if truth:
            (tmp / "truth").mkdir()
            with open(tmp / "truth" / "spheres.csv", "w", newline="", encoding="utf-8") as fh:
                wr = csv.writer(fh)
                wr.writerow(["col", "row", "radius_px", "kind"])
                for s in sc.spheres:
                    wr.writerow([f"{s['centre_px'][0]:.3f}", f"{s['centre_px'][1]:.3f}", f"{s['radius_px']:.3f}",
                                 s["kind"]])
            with open(tmp / "truth" / "lights_positions_mm.csv", "w", newline="", encoding="utf-8") as fh:
                wr = csv.writer(fh)
                wr.writerow(["x_mm", "y_mm", "z_mm"])
                for p in sc.light_positions_mm:
                    wr.writerow([f"{v:.6f}" for v in p])
            (tmp / "truth" / "spheres.json").write_text(json.dumps({"spheres": sc.spheres}, indent=1),
                                                        encoding="utf-8")
            written += ["truth/spheres.csv", "truth/lights_positions_mm.csv", "truth/spheres.json"]
    return [folder / w for w in written]
