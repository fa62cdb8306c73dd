#!/usr/bin/env python3
"""Why two mirror spheres of one capture disagree: the figures behind docs/decisions/spheres.md's analysis of
PSBox's LightProbe-1 and -2 (two spheres cropped from the same frames), measured on ``uvps calibrate``'s own fits.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/analyse_sphere_pair.py A=FOLDER B=FOLDER \\
        --crop A=COL,ROW --crop B=COL,ROW [--reference A=FILE --reference B=FILE] \\
        [--focal-px F ...] [--principal COL,ROW ...] [--circle A=COL,ROW,RADIUS] [--lights A=FILE] \
        [--distortion PCT ...]

``FOLDER``: one sphere's lamp images (as ``uvps calibrate --spheres`` reads them); ``--crop``: where its images
were cut from the full frame (column, row of the top-left pixel, rows counted down from the frame's top:
PSBox's ``data/ManualData/probes_bbox.txt`` counts rows up, 991-1990 and 991-1940, so LightProbe-2's top row lies
50 rows below LightProbe-1's: ``A=0,990 B=2750,1040``). Prints, per lamp and as median / max (deg):

1. the two spheres' directions as ``uvps calibrate`` gives them (orthographic camera, view (0, 0, 1)), their
   difference split along the baseline (``benchmark_spheres_real.split_by_baseline``: in the plane of the
   baseline and the ray, where a lamp's parallax lies, and across it, where no lamp position does);
2. the same highlights read through a pinhole camera (focal length ``--focal-px`` in pixels of the full
   frame, principal point ``--principal``, default the spheres' midpoint): each highlight pixel's ray meets its
   sphere (the sphere's distance from its apparent radius), ``l = 2 (n . v) n - v`` with ``v`` toward the
   camera from that point; the difference split along the spheres' baseline in 3-D; the lamps' distances
   where the two rays meet (from the spheres' midpoint), over the camera's; and the least across-baseline median
   over a grid of focal lengths and principal points; with ``--distortion``, the orthographic split with a radial
   lens distortion taken out of the highlights and the rims; with ``--lights``, each sphere's pinhole directions
   against its published ones (one sphere alone: these only, about its images' centre);
3. the highlights themselves (8-bit grey, mean of the channels): the saturated core's length and width (4
   sigma) and long axis, how far its centroid moves between the clip levels 252 and 235, and the split of the
   directions the centroids at clip levels 252-200 give;
4. with ``--reference`` (a room-lit picture of the sphere): its rim (sub-pixel gradient maxima along rays,
   the stand's lower 130 deg left out) fitted with a circle and with an ellipse;
5. ``--off-axis-example`` alone: a computed macro geometry (a 5 mm mirror ball 0-15 mm off the axis of a camera
   150 mm above the painting, lamps on a 100 mm dome): how far the orthographic reading is from the true directions.
"""
import argparse
import json
import math
import sys
import tempfile
from pathlib import Path

import cv2
import numpy as np
from scipy import ndimage, optimize

sys.path.insert(0, str(Path(__file__).resolve().parent))
import benchmark_spheres_real as bsr  # noqa: E402

from uvps.commands import COMMANDS  # noqa: E402
from uvps.core.spheres import triangulate  # noqa: E402

Z = np.array([0.0, 0.0, 1.0])
CLIPS = (252, 240, 220, 200)


def _fit(folder, circle=None):
    """uvps calibrate's directions (K, 3), circle centre (col, row) and radius on one sphere's images; ``circle``
    "COL,ROW,RADIUS" given instead of found (``--sphere-circles``)."""
    with tempfile.TemporaryDirectory() as tmp:
        inputs = {"spheres": [folder]}
        if circle:
            (Path(tmp) / "circle.csv").write_text(f"col,row,radius_px\n{circle}\n")
            inputs["sphere_circles"] = str(Path(tmp) / "circle.csv")
        COMMANDS["calibrate"](inputs, {"pixel_size_um": 100.0}, Path(tmp) / "CAL")
        doc = json.loads((Path(tmp) / "CAL" / "calibration.json").read_text())
    s = doc["spheres"][0]
    return np.array([lamp["direction"] for lamp in doc["lamps"]]), np.array(s["centre_px"][:2]), s["radius_px"]


def _highlight_px(dirs, centre, radius):
    """The highlight pixels (K, 2: col, row) the orthographic directions came from."""
    n = dirs + Z
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    return np.c_[centre[0] + radius * n[:, 0], centre[1] - radius * n[:, 1]]


def _ray(px, principal, f):
    v = np.array([px[0] - principal[0], principal[1] - px[1], -f])
    return v / np.linalg.norm(v)


def pinhole_sphere(centre, radius, principal, f):
    """A sphere's centre in the camera's frame (x right, y up, z toward the camera; radius 1) and its off-axis
    angle (deg), from its image's centre and radius (full-frame px): the outline's centre and radius along
    the radial line are ``f (tan(t + a) + tan(t - a)) / 2`` and ``f (tan(t + a) - tan(t - a)) / 2``."""
    s = math.hypot(centre[0] - principal[0], centre[1] - principal[1])

    def eq(x):
        t, a = x
        return [f * (math.tan(t + a) + math.tan(t - a)) / 2 - s, f * (math.tan(t + a) - math.tan(t - a)) / 2 - radius]

    t, a = optimize.fsolve(eq, [math.atan(s / f), math.atan(radius / f)])
    az = np.array([centre[0] - principal[0], principal[1] - centre[1]]) / max(s, 1e-9)
    u = np.array([math.sin(t) * az[0], math.sin(t) * az[1], -math.cos(t)])
    return u / math.sin(a), math.degrees(t)


def pinhole_directions(px, centre, radius, principal, f):
    """Each highlight pixel's lamp direction through a pinhole camera: (K, 3), the sphere's centre, off-axis
    angle (deg) and the surface points (K, 3)."""
    C, off = pinhole_sphere(centre, radius, principal, f)
    out, pts = [], []
    for p in px:
        d = _ray(p, principal, f)
        b = d @ C
        t = b - math.sqrt(max(b * b - (C @ C - 1.0), 0.0))
        n = t * d - C
        n /= np.linalg.norm(n)
        v = -d
        lamp = 2 * (n @ v) * n - v
        out.append(lamp / np.linalg.norm(lamp))
        pts.append(t * d)
    return np.array(out), C, off, np.array(pts)


def _summary(d1, d2, baseline):
    a = bsr._angles(d1, d2)
    inp, acr = bsr.split_by_baseline(d1, d2, baseline)
    return (f"apart {np.median(a):.2f} / {a.max():.2f}, in the plane {inp.min():+.2f} to {inp.max():+.2f}, "
            f"across {np.median(np.abs(acr)):.2f} / {np.abs(acr).max():.2f}"), inp, acr


def perspective(fits, principal, f):
    """Part 2 at one camera: the split and the lamps' distances over the spheres'."""
    (d1, c1, r1), (d2, c2, r2) = fits
    e1, C1, o1, p1 = pinhole_directions(_highlight_px(d1, c1, r1), c1, r1, principal, f)
    e2, C2, o2, p2 = pinhole_directions(_highlight_px(d2, c2, r2), c2, r2, principal, f)
    text, _, acr = _summary(e1, e2, C2 - C1)
    mid = 0.5 * (C1 + C2)
    dist = []
    for k in range(len(e1)):
        pos = triangulate(np.array([p1[k], p2[k]]), np.array([e1[k], e2[k]]), np.full(2, 1e-3))[0]
        dist.append(np.linalg.norm(pos - mid) / np.linalg.norm(mid))
    return text, (o1, o2), np.array(dist), float(np.median(np.abs(acr)))


def _core(img, seed, clip):
    lab, _ = ndimage.label(img >= clip)
    lab_id = lab[int(round(seed[1])), int(round(seed[0]))]
    ys, xs = np.nonzero(lab == lab_id) if lab_id else (np.array([seed[1]]), np.array([seed[0]]))
    return xs.astype(float), ys.astype(float)


def _centroid_dirs(grey, px, centre, radius, clip):
    out = []
    for img, seed in zip(grey, px):
        xs, ys = _core(img, seed, clip)
        x, y = (xs.mean() - centre[0]) / radius, (centre[1] - ys.mean()) / radius
        m = np.array([x, y, math.sqrt(max(0.0, 1 - x * x - y * y))])
        out.append(2 * m[2] * m - Z)
    return np.array(out)


def highlights(name, grey, px, centre, radius):
    """Part 3 for one sphere: the saturated cores' shape and how their centroid moves with the clip level."""
    size, axis, move = [], [], []
    for img, seed in zip(grey, px):
        xs, ys = _core(img, seed, 252)
        w, V = np.linalg.eigh(np.cov(np.c_[xs, ys].T))
        size.append((4 * math.sqrt(w[1]), 4 * math.sqrt(w[0])))
        axis.append(math.degrees(math.atan2(-V[1, 1], V[0, 1])) % 180)
        lo = _core(img, seed, 235)
        move.append((abs(lo[0].mean() - xs.mean()), abs(lo[1].mean() - ys.mean())))
    size, move = np.array(size), np.array(move)
    to_deg = math.degrees(2 / radius)
    print(f"{name}: saturated core {np.median(size[:, 0]):.0f} x {np.median(size[:, 1]):.0f} px (4 sigma, median), "
          f"long axis {np.round(axis).astype(int).tolist()} deg from +x\n"
          f"  centroid moves between clip 252 and 235: x {np.round(move[:, 0], 1).tolist()}, "
          f"y {np.round(move[:, 1], 1).tolist()} px (median x {np.median(move[:, 0]):.1f}, "
          f"y {np.median(move[:, 1]):.1f} px = {np.median(move[:, 0]) * to_deg:.2f}, "
          f"{np.median(move[:, 1]) * to_deg:.2f} deg of direction)")


def rim(name, path, centre, radius):
    """Part 4: a room-lit picture's rim fitted with a circle and with an ellipse (cv2.fitEllipse)."""
    g = ndimage.gaussian_filter(cv2.imread(str(path)).astype(float).mean(axis=2), 1.0)
    pts = []
    for deg in np.arange(0.0, 360.0, 0.5):
        if 205 < deg < 335:           # the stand
            continue
        phi = math.radians(deg)
        rr = np.linspace(0.92 * radius, 1.08 * radius, 400)
        xs, ys = centre[0] + rr * math.cos(phi), centre[1] - rr * math.sin(phi)
        if xs.min() < 1 or ys.min() < 1 or xs.max() > g.shape[1] - 2 or ys.max() > g.shape[0] - 2:
            continue
        d = np.gradient(ndimage.map_coordinates(g, [ys, xs], order=1))
        i = int(np.argmax(d))
        if 2 <= i < len(d) - 2 and d[i] >= 1.5:
            off = 0.5 * (d[i - 1] - d[i + 1]) / (d[i - 1] - 2 * d[i] + d[i + 1])
            r = rr[i] + off * (rr[1] - rr[0])
            pts.append([centre[0] + r * math.cos(phi), centre[1] - r * math.sin(phi)])
    pts = np.array(pts, np.float32)
    n_all = len(pts)

    def circle(q):
        return optimize.least_squares(lambda p: np.hypot(q[:, 0] - p[0], q[:, 1] - p[1]) - p[2],
                                      [centre[0], centre[1], radius])

    res = np.abs(circle(pts).fun)
    pts = pts[res < 3 * np.median(res) + 0.5]           # a reflection's edge taken for the rim
    fit = circle(pts)
    (ex, ey), (a, b), ang = cv2.fitEllipse(pts)
    major = (ang if a >= b else ang + 90.0) % 180.0     # cv2: degrees clockwise in the image (rows down)
    print(f"{name} rim: {len(pts)} of {n_all} points; circle ({fit.x[0]:.1f}, {fit.x[1]:.1f}), {fit.x[2]:.1f} px, "
          f"rms {np.sqrt(np.mean(fit.fun ** 2)):.2f}; ellipse ({ex:.1f}, {ey:.1f}), semi-axes {max(a, b) / 2:.1f} x "
          f"{min(a, b) / 2:.1f} px (ratio {max(a, b) / min(a, b):.4f}), long axis {(180 - major) % 180:.0f} deg "
          "from +x (y up)")


def _undistort(px, principal, k):
    """Pixels with the radial distortion ``r_d = r_u (1 + k r_u^2)`` about ``principal`` taken out."""
    d = np.asarray(px, float) - principal
    ru = d.copy()
    for _ in range(30):
        ru = d / (1 + k * (ru ** 2).sum(axis=-1, keepdims=True))
    return principal + ru


def undistorted(dirs, centre, radius, principal, k):
    """A sphere's orthographic directions and image centre with a radial lens distortion taken out of its highlight
    pixels and its rim (the rim's points undistorted and averaged for the centre and radius)."""
    t = np.radians(np.arange(0.0, 360.0, 2.0))
    rim = _undistort(np.c_[centre[0] + radius * np.cos(t), centre[1] + radius * np.sin(t)], principal, k)
    c = rim.mean(axis=0)
    r = float(np.hypot(*(rim - c).T).mean())
    q = _undistort(_highlight_px(dirs, centre, radius), principal, k)
    x, y = (q[:, 0] - c[0]) / r, (c[1] - q[:, 1]) / r
    m = np.c_[x, y, np.sqrt(np.clip(1 - x * x - y * y, 0, None))]
    return 2 * m[:, 2:] * m - Z, c


def mirror_point(centre, lamp):
    """The surface point of the unit sphere at ``centre`` (camera at the origin) where ``lamp`` reflects into the
    camera: its normal halves the angle between the camera and the lamp (fixed-point iteration)."""
    n = -centre / np.linalg.norm(centre)
    for _ in range(500):
        x = centre + n
        to_cam, to_lamp = -x / np.linalg.norm(x), (lamp - x) / np.linalg.norm(lamp - x)
        n = (to_cam + to_lamp) / np.linalg.norm(to_cam + to_lamp)
    return centre + n


def off_axis_example(*, radius_mm=2.5, distance_mm=150.0, dome_mm=100.0, offsets_mm=(0.0, 6.0, 12.0, 15.0)):
    """How far an orthographic reading of a mirror sphere off the lens axis is from the true directions (from its
    centre): a pinhole camera ``distance_mm`` above the painting, the sphere ``offsets_mm`` off the axis on the
    painting, lamps on a dome of radius ``dome_mm`` around the axis at 30-75 deg elevation, every 45 deg."""
    f = 6000.0
    for off in offsets_mm:
        C = np.array([off, 0.0, radius_mm - distance_mm]) / radius_mm
        lamps = [np.array([dome_mm * math.cos(e) * math.cos(a), dome_mm * math.cos(e) * math.sin(a),
                           dome_mm * math.sin(e) - distance_mm]) / radius_mm
                 for e in np.radians([30, 45, 60, 75]) for a in np.radians(np.arange(0, 360, 45))]
        pts = [mirror_point(C, P) for P in lamps]
        px = np.array([[f * x[0] / -x[2], -f * x[1] / -x[2]] for x in pts])
        d, t = np.linalg.norm(C), math.acos(-C[2] / np.linalg.norm(C))
        a = math.asin(1.0 / d)
        centre = np.array([f * (math.tan(t + a) + math.tan(t - a)) / 2, 0.0])
        radius = f * (math.tan(t + a) - math.tan(t - a)) / 2
        n = np.c_[(px[:, 0] - centre[0]) / radius, -(px[:, 1] - centre[1]) / radius]
        n = np.c_[n, np.sqrt(1 - (n ** 2).sum(axis=1))]
        ortho = 2 * n[:, 2:] * n - Z
        err = bsr._angles(ortho, np.array([(P - C) / np.linalg.norm(P - C) for P in lamps]))
        err_pt = bsr._angles(ortho, np.array([(P - x) / np.linalg.norm(P - x) for P, x in zip(lamps, pts)]))
        print(f"5. a {2 * radius_mm:g} mm mirror sphere {off:g} mm off the axis, camera {distance_mm:g} mm above "
              f"({math.degrees(t):.1f} deg off), lamps on a {dome_mm:g} mm dome: orthographic reading "
              f"{np.median(err):.2f} / {err.max():.2f} deg from the true directions from its centre, "
              f"{np.median(err_pt):.2f} / {err_pt.max():.2f} from the highlight's point")


def _images(folder):
    files = sorted(p for p in Path(folder).iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png", ".tif")
                   and not p.stem.lower().startswith("ref"))
    return [cv2.imread(str(p)).astype(float).mean(axis=2) for p in files]


def _matched_areas(fits):
    """Part 3: per lamp, the smaller core (area over the radius squared, clip 252) clipped lower until it matches
    the other's; the directions of both centroids. Returns (d1, d2, the area ratios)."""
    out, ratios = ([], []), []
    for k in range(len(fits[0][0])):
        seeds = [_highlight_px(d, c, r)[k] for d, c, r, _ in fits]
        area = [len(_core(g[k], sd, 252)[0]) / r ** 2 for (_, _, r, g), sd in zip(fits, seeds)]
        ratios.append(area[1] / area[0])
        small = int(np.argmin(area))
        for i, ((_, c, r, g), sd) in enumerate(zip(fits, seeds)):
            clip = 252
            while i == small and clip > 100 and len(_core(g[k], sd, clip)[0]) / r ** 2 < area[1 - small]:
                clip -= 1
            out[i].append(_centroid_dirs([g[k]], [sd], c, r, clip)[0])
    return np.array(out[0]), np.array(out[1]), np.array(ratios)


def _against_published(names, full, lights, principal, f):
    parts = []
    for n, (d, c, r) in zip(names, full):
        if n in lights:
            e = pinhole_directions(_highlight_px(d, c, r), c, r, principal, f)[0]
            a = bsr._angles(e, bsr._published(lights[n]))
            parts.append(f"{n} against its published directions {np.median(a):.2f} / {a.max():.2f}")
    return ("; " + "; ".join(parts)) if parts else ""


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("spheres", nargs="*", help="NAME=FOLDER (one sphere, or two of one capture)")
    ap.add_argument("--off-axis-example", action="store_true",
                    help="only the rendered geometry of part 5 (a macro field's corner sphere), no capture")
    ap.add_argument("--crop", action="append", default=[], help="NAME=COL,ROW (rows from the frame's top)")
    ap.add_argument("--reference", action="append", default=[], help="NAME=FILE: a room-lit picture")
    ap.add_argument("--circle", action="append", default=[],
                    help="NAME=COL,ROW,RADIUS: that sphere's circle (px of its images) instead of the one found")
    ap.add_argument("--lights", action="append", default=[], help="NAME=FILE: that sphere's published directions")
    ap.add_argument("--focal-px", type=float, nargs="+", default=[4000, 8000, 12000, 20000, 50000])
    ap.add_argument("--distortion", type=float, nargs="*", default=[],
                    help="radial lens distortions to take out (percent at --distortion-radius px from the principal "
                         "point; negative: barrel), for the orthographic split")
    ap.add_argument("--distortion-radius", type=float, default=2300.0)
    ap.add_argument("--principal", action="append", default=[],
                    help="COL,ROW in the full frame (default: two spheres' midpoint, one sphere's image centre)")
    args = ap.parse_args(argv)
    if args.off_axis_example or not args.spheres:
        off_axis_example()
        return 0
    names, folders = zip(*(s.split("=", 1) for s in args.spheres))
    crops = {n: np.array(v.split(","), float) for n, v in (c.split("=", 1) for c in args.crop)}
    circles = dict(c.split("=", 1) for c in args.circle)
    fits = [_fit(folder, circles.get(n)) + (_images(folder),) for n, folder in zip(names, folders)]
    full = [(d, c + crops.get(n, np.zeros(2)), r) for n, (d, c, r, _) in zip(names, fits)]
    if args.principal:
        principals = [np.array(p.split(","), float) for p in args.principal]
    elif len(full) == 2:
        principals = [0.5 * (full[0][1] + full[1][1])]
    else:
        principals = [(np.array(fits[0][3][0].shape[::-1]) - 1) / 2.0 + crops.get(names[0], np.zeros(2))]
    lights = dict(s.split("=", 1) for s in args.lights)
    if len(full) == 2:
        _pair(full, [lights.get(n) for n in names])
    for pp in principals:
        for f in args.focal_px:
            print(_camera_line(names, full, pp, f) + _against_published(names, full, lights, pp, f))
    if len(full) == 2:
        _least_across(full)
        _distortions(full, principals, args)
    for n, (d, c, r, g) in zip(names, fits):
        highlights(f"3. {n}", g, _highlight_px(d, c, r), c, r)
    if len(full) == 2:
        base = full[1][1] - full[0][1]
        for clip in CLIPS:
            dd = [_centroid_dirs(g, _highlight_px(d, c, r), c, r, clip) for d, c, r, g in fits]
            print(f"  centroids at clip {clip}: {_summary(dd[0], dd[1], [base[0], -base[1], 0.0])[0]}")
        d1, d2, ratio = _matched_areas(fits)
        print(f"  cores' areas at clip 252, second over first: {ratio.min():.2f}-{ratio.max():.2f}; the smaller "
              f"clipped lower to match: {_summary(d1, d2, [base[0], -base[1], 0.0])[0]}")
    refs = dict(s.split("=", 1) for s in args.reference)
    for n, (d, c, r, _) in zip(names, fits):
        if n in refs:
            rim(f"4. {n}", refs[n], c, r)
    return 0


def _pair(full, lights):
    text, inp, acr = _summary(full[0][0], full[1][0], _baseline(full[0][1], full[1][1]))
    print(f"1. orthographic (uvps calibrate): {text}\n  in the plane {np.round(inp, 2).tolist()}\n"
          f"  across {np.round(acr, 2).tolist()}: mean {acr.mean():+.2f}, rms about it {acr.std():.2f}")
    if all(lights):
        pub = [bsr._published(f) for f in lights]
        print(f"  the published directions: {_summary(pub[0], pub[1], _baseline(full[0][1], full[1][1]))[0]}")


def _camera_line(names, full, pp, f):
    head = f"2. pinhole f {f:.0f} px, principal ({pp[0]:.0f}, {pp[1]:.0f})"
    if len(full) == 1:
        d, c, r = full[0]
        return head + f": off-axis {pinhole_sphere(c, r, pp, f)[1]:.1f} deg"
    text, off, dist, _ = perspective(full, pp, f)
    return (head + f": off-axis {off[0]:.1f}, {off[1]:.1f} deg; {text}; lamps {dist.min():.2f}-{dist.max():.2f} x "
            "the camera's distance from the spheres")


def _distortions(full, principals, args):
    _, _, acr0 = _summary(full[0][0], full[1][0], _baseline(full[0][1], full[1][1]))
    for pp in principals:
        for pct in args.distortion:
            k = pct / 100.0 / args.distortion_radius ** 2
            (e1, c1), (e2, c2) = (undistorted(d, c, r, pp, k) for d, c, r in full)
            text, _, acr = _summary(e1, e2, _baseline(c1, c2))
            print(f"  lens distortion {pct:+g} % at {args.distortion_radius:.0f} px from ({pp[0]:.0f}, {pp[1]:.0f}) "
                  f"taken out: {text} (across moved {np.abs(acr - acr0).max():.2f} at most)")


def _baseline(c1, c2):
    return [c2[0] - c1[0], c1[1] - c2[1], 0.0]


def _least_across(full):
    grid = [(perspective(full, np.array([cx, cy]), f)[3], f, cx, cy)
            for f in (2500, 5000, 10000, 20000, 60000)
            for cx in np.linspace(-2000, 6000, 5) for cy in np.linspace(-2000, 5000, 5)]
    best = min(grid)
    print(f"  least across median over f 2500-60000 px and principal points (-2000..6000, -2000..5000): "
          f"{best[0]:.2f} deg (f {best[1]:.0f}, principal {best[2]:.0f}, {best[3]:.0f})")


if __name__ == "__main__":
    sys.exit(main())
