#!/usr/bin/env python3
"""How well a glossy or mirror sphere's circle is found when an arc of its limb is not its rim: the lower third
of the limb reflecting the lit ground (``make_sphere_capture(..., limb_reflection=A)``: a band 4.6 % of the
radius wide inside the rim, shaded as the ground), a stand in front of the lower part (``stand=True``), and the
lens's blur (a Gaussian of ``sigma`` px on every picture). The figures of docs/decisions/spheres.md's "The rim's
circle: a band from its own scatter, every view's arcs".

    OMP_NUM_THREADS=1 .venv/bin/python scripts/analyse_sphere_rim.py [--seeds 3 4 5] [--kinds mirror glossy]

One 4 mm sphere (80 px of 50 um) near the centre of a 480 x 360 px frame, 8 lamps at 20-60 deg of elevation
(``make_capture(..., seed=SEED)``), black level 300 counts; ``detect_spheres`` on the pictures alone. Per row:
each seed's circle minus the true one (centre col, row; radius; px).
"""
import argparse

import numpy as np
from scipy import ndimage

from uvps.core.spheres import detect_spheres
from uvps.testing.synthetic import make_capture
from uvps.testing.synthetic_spheres import SphereSpec, make_sphere_capture

PX = 50.0


def circle_error(*, seed, kind, reflection, blur, stand):
    """The detected circle minus the true one (d col, d row, d radius; px), or None when none is found."""
    cap = make_capture(shape=(360, 480), n_lights=8, seed=seed, pixel_size_um=PX, rgb=False, black_level=300.0)
    sc = make_sphere_capture(cap, [SphereSpec(kind, (0.5, 0.45), 4.0)], stand=stand, limb_reflection=reflection)
    images = sc.images.astype(np.float32) - 300.0
    if blur:
        images = ndimage.gaussian_filter(images, (0, blur, blur))
    found = detect_spheres(images)
    if not found:
        return None
    true = sc.spheres[0]
    return (found[0].centre_px[0] - true["centre_px"][0], found[0].centre_px[1] - true["centre_px"][1],
            found[0].radius_px - true["radius_px"])


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[3, 4, 5])
    ap.add_argument("--kinds", nargs="+", default=["mirror", "glossy"], choices=["mirror", "glossy"])
    ap.add_argument("--reflections", type=float, nargs="+", default=[0.0, 0.8])
    ap.add_argument("--blurs", type=float, nargs="+", default=[0.0, 1.5, 3.0])
    args = ap.parse_args(argv)
    print("| kind | ground reflected | blur (px) | stand | " + " | ".join(f"seed {s}" for s in args.seeds) + " |")
    print("|---|---|---|---|" + "---|" * len(args.seeds))
    for kind in args.kinds:
        for refl in args.reflections:
            for blur in args.blurs:
                for stand in (False, True):
                    cells = []
                    for seed in args.seeds:
                        e = circle_error(seed=seed, kind=kind, reflection=refl, blur=blur, stand=stand)
                        cells.append("none" if e is None else "%+.2f %+.2f %+.2f" % e)
                    print(f"| {kind} | {refl:g} | {blur:g} | {'yes' if stand else 'no'} | " + " | ".join(cells) + " |",
                          flush=True)


if __name__ == "__main__":
    main()
