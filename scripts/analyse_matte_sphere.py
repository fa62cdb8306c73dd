#!/usr/bin/env python3
"""Why a real matte sphere's lamps come where they come: the figures behind docs/decisions/spheres.md's
grey-ball analysis, measured on one matte sphere capture with ``uvps.core.spheres``' own fits.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/analyse_matte_sphere.py FOLDER LIGHTS \\
        [--against NAME=LIGHTS ...] [--circle COL ROW RADIUS]
    OMP_NUM_THREADS=1 .venv/bin/python scripts/analyse_matte_sphere.py --rough

``FOLDER``: the lamps' images (as ``uvps calibrate --spheres`` reads them; one sphere); ``LIGHTS``: a published
directions file (benchmark_spheres_real.py's format); ``--against``: other directions to compare with (e.g. a
chrome ball's from ``uvps calibrate``, saved as K x 3 numbers); ``--circle``: a circle to compare the found rim
with (e.g. a hand-drawn mask's). Prints, each against the published directions (median / max deg):

1. each lamp's additive term fitted freely (over ``|b|``) beside what its attached shadow shows;
2. how far a 2 % gain across the disc (radial, then linear in y) moves the lamps with the term free and held;
3. the lamps fitted on each half of the disc alone against the whole disc's;
4. ``uvps calibrate``'s steps: the term free or held, the circle refined or the rim kept, the gain or none.

``--rough``: rendered rough balls instead (:func:`rough_balls`), where holding the additive term stops helping.
"""
import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import benchmark_spheres_real as bsr  # noqa: E402

import uvps.core.spheres as sp  # noqa: E402
from uvps.core.sphere_find import Sphere  # noqa: E402
from uvps.files.io import read_capture  # noqa: E402


def _dirs(vals, normals, sat, offsets=None):
    out = []
    for k in range(len(vals)):
        fit = sp._fit_matte(vals[k], normals, sat, None if offsets is None else offsets[k])
        out.append(fit[0] / np.linalg.norm(fit[0]))
    return np.array(out)


def _fmt(d, refs):
    return "  ".join(f"{name} {np.median(a):.2f} / {a.max():.2f}"
                     for name, a in ((n, bsr._angles(d, r)) for n, r in refs.items()))


def rough_balls(sigmas=(0.05, 0.1, 0.15, 0.2, 0.25, 0.3, 0.35), falloff=0.3):
    """``--rough``: rendered rough (Oren-Nayar) balls under the UW-like lamps (tests/test_spheres.py's
    ``_ball_under_front_lamps``): the statistic ``_shadow_offsets`` gates on, and the lamps' errors with the
    additive term held at the shadows' level and free."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
    from test_spheres import _angles, _ball_under_front_lamps
    orig = sp._shadow_offsets, sp.MATTE_SHADOW_AGREE
    print("roughness (rad), lit part over the shadow (|b|), held / free: median / max deg")
    for sigma in sigmas:
        imgs, lamps, circ = _ball_under_front_lamps(sigma=sigma, falloff=falloff)
        disc = sp._Disc(Sphere(circ[:2], circ[2], "matte", "given"), imgs.shape[1:], 100.0)
        vals = sp._disc_values(imgs, (0, imgs.shape[1], 0, imgs.shape[2]), disc)
        stat = []
        for k in range(len(vals)):
            fit = sp._fit_matte(vals[k], disc.normals, None)
            nb = np.linalg.norm(fit[0])
            dark = disc.normals @ (fit[0] / nb) < -sp.MATTE_SHADOW_COS
            if dark.sum() >= sp.MATTE_SHADOW_MIN * len(disc.normals):
                stat.append((dark.sum(), (fit[1] - np.median(vals[k][dark])) / nb))
        stat = sorted(stat, reverse=True)[:max(1, len(stat) // 4)]
        err = {}
        for mode in ("held", "free"):
            try:
                sp.MATTE_SHADOW_AGREE = np.inf
                if mode == "free":
                    sp._shadow_offsets = lambda *a, **k: None
                cal = sp.calibrate_spheres(imgs, pixel_size_um=100.0, saturation=None)
            finally:
                sp._shadow_offsets, sp.MATTE_SHADOW_AGREE = orig
            e = _angles(cal.directions, lamps)
            err[mode] = f"{np.median(e):.2f} / {e.max():.2f}"
        print(f"   {sigma:.2f}  {np.median([t[1] for t in stat]):.3f}  held {err['held']}  free {err['free']}")


def main(argv=None):
    if argv is None and "--rough" in sys.argv[1:] or argv is not None and "--rough" in argv:
        rough_balls()
        return 0
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder")
    ap.add_argument("lights")
    ap.add_argument("--against", action="append", default=[], help="NAME=LIGHTS")
    ap.add_argument("--circle", type=float, nargs=3, metavar=("COL", "ROW", "RADIUS"))
    args = ap.parse_args(argv)
    refs = {"published": bsr._published(args.lights)}
    for spec in args.against:
        name, path = spec.split("=", 1)
        refs[name] = bsr._published(path)
    cap = read_capture(args.folder, pixel_size_um=100.0)
    images, saturation = np.asarray(cap.images), cap.saturation
    sat = None if saturation is None else 0.995 * float(saturation)
    found = sp.detect_spheres(images)[0]
    print(f"rim found: ({found.centre_px[0]:.1f}, {found.centre_px[1]:.1f}), {found.radius_px:.1f} px"
          + (f"; given circle ({args.circle[0]:.1f}, {args.circle[1]:.1f}), {args.circle[2]:.1f}" if args.circle else ""))
    shape = images.shape[1:3]
    whole = (0, shape[0], 0, shape[1])
    disc = sp._Disc(Sphere(found.centre_px, found.radius_px, "matte", "found"), shape, 100.0)
    vals = sp._disc_values(images, whole, disc)
    n = disc.normals

    print("\n1. additive term: lamp, angle from the view (deg), fitted c / |b|, attached shadow's median (counts), |b|")
    held = sp._shadow_offsets(vals, n, sat)
    for k in range(len(vals)):
        fit = sp._fit_matte(vals[k], n, sat)
        nb = np.linalg.norm(fit[0])
        l = fit[0] / nb
        dark = n @ l < -sp.MATTE_SHADOW_COS
        level = f"{np.median(vals[k][dark]):6.1f}" if dark.sum() >= 20 else "  none"
        print(f"   {k + 1:3d} {np.degrees(np.arccos(l[2])):5.1f} {fit[1] / nb:+.3f} {level} {nb:7.1f}")
    print("   held:", "no (Lambert's law with the shadow's term does not hold)" if held is None
          else np.round(held, 1).tolist())

    print("\n2. a 2 % gain across the disc moves the lamps (median / max deg):")
    zero = np.zeros(len(vals)) if held is None else held
    free0, held0 = _dirs(vals, n, sat), _dirs(vals, n, sat, zero)
    for name, g in (("radial 1 - 0.02 rho^2", 1 - 0.02 * (n[:, 0] ** 2 + n[:, 1] ** 2)), ("linear 1 - 0.02 n_y", 1 - 0.02 * n[:, 1])):
        v = (vals - zero[:, None]) * g + zero[:, None]
        a, b = bsr._angles(_dirs(v, n, sat), free0), bsr._angles(_dirs(v, n, sat, zero), held0)
        print(f"   {name}: term free {np.median(a):.2f} / {a.max():.2f}, held {np.median(b):.2f} / {b.max():.2f}")

    print("\n3. the lamps fitted (n . b + c) on half the disc against the whole disc's:")
    whole4 = np.array([sp._fit_matte_numpy_terms(vals[k], n, sat, 4)[0] for k in range(len(vals))])
    whole4 /= np.linalg.norm(whole4, axis=1, keepdims=True)
    for name, half in (("left", n[:, 0] < 0), ("right", n[:, 0] > 0), ("upper", n[:, 1] > 0), ("lower", n[:, 1] < 0)):
        d = np.array([sp._fit_matte_numpy_terms(vals[k][half], n[half], sat, 4)[0] for k in range(len(vals))])
        a = bsr._angles(d / np.linalg.norm(d, axis=1, keepdims=True), whole4)
        print(f"   {name:6s} {np.median(a):.2f} / {a.max():.2f}")

    print("\n4. uvps calibrate's steps against the references (median / max deg); today's:",
          _fmt(sp.calibrate_spheres(images, pixel_size_um=100.0, saturation=saturation).directions, refs))
    circles = [("rim", found)]
    if args.circle:
        circles.append(("given circle", Sphere(tuple(args.circle[:2]), args.circle[2], "matte", "given")))
    for cname, circ in circles:
        d = sp._Disc(Sphere(circ.centre_px, circ.radius_px, "matte", "x"), shape, 100.0)
        v = sp._disc_values(images, whole, d)
        off = sp._shadow_offsets(v, d.normals, sat)
        print(f"   {cname}, term free, no gain:  {_fmt(_dirs(v, d.normals, sat), refs)}")
        if off is not None:
            print(f"   {cname}, term held, no gain:  {_fmt(_dirs(v, d.normals, sat, off), refs)}")
    for term in ("free", "held"):
        for move in (sp.MATTE_CIRCLE_MOVE, 0.0):
            orig = sp._shadow_offsets, sp.MATTE_CIRCLE_MOVE, sp.MATTE_KEEP_RIM
            try:
                if term == "free":
                    sp._shadow_offsets = lambda *a, **k: None
                sp.MATTE_CIRCLE_MOVE = move if move > 0 else 1e-9
                sp.MATTE_KEEP_RIM = False           # the circle where the shading puts it, bounds or not
                cal = sp.calibrate_spheres(images, pixel_size_um=100.0, saturation=saturation)
            finally:
                sp._shadow_offsets, sp.MATTE_CIRCLE_MOVE, sp.MATTE_KEEP_RIM = orig
            s = cal.spheres[0]
            what = f"circle refined (bounds {move:.0%})" if move > 0 else "rim kept"
            print(f"   term {term}, {what}, gain: circle ({s.centre_px[0]:.1f}, {s.centre_px[1]:.1f}), "
                  f"{s.radius_px:.1f}; {_fmt(cal.directions, refs)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
