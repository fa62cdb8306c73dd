#!/usr/bin/env python3
"""Real sphere captures through ``uvps calibrate`` with nothing but the lamps' images: no circle, no kind,
no reference picture. Each capture's directions are compared with its published ones where it has them,
and the captures given as one capture's spheres with each other.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/benchmark_spheres_real.py \\
        [--capture NAME=FOLDER[:LIGHTS]] ... [--same-lamps NAME,NAME] ...

Default: ``../shared/data/sphere_mirror_psbox`` (PSBox's LightProbe-2, MIT) with its
``light_directions.txt``. ``LIGHTS`` is a published directions file: 3 x K or K x 3 numbers, an optional
first line holding K alone (x right, y up, z toward the camera). ``--same-lamps A,B``: two spheres of one
capture (cropped from the same frames, e.g. PSBox's LightProbe-1 and -2), whose rays must meet: with ``--crop``,
the part of their difference across the spheres' baseline, which no lamp position gives (nor, measured on
PSBox's pair, the camera's perspective: scripts/analyse_sphere_pair.py).
Other public captures are not shipped with the project: fetch them yourself (docs/benchmarks.md,
"Calibration and spheres", names them and their sources).

``--doc`` writes docs/benchmarks.md's "Real sphere captures" table (section ``spheres_real``:
:func:`render_doc`) and docs/benchmarks/spheres_real.json: a capture measured replaces the kept row of its
NAME, keeping that row's description of its source (``label``) and ``note``; the other rows stay
(scripts/benchdoc.py).
"""
import argparse
import json
import math
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from uvps.commands import COMMANDS

DOC_SECTION = "spheres_real"
#: Bold in the doc's table: a direction within this of the published one (deg).
DOC_BOLD_DEG = 1.0

DATA = next((p / "shared" / "data" for p in Path(__file__).resolve().parents if (p / "shared" / "data").is_dir()),
            Path("/work/shared/data"))


def _published(path):
    rows = [ln.split() for ln in Path(path).read_text().splitlines() if ln.strip()]
    if len(rows[0]) == 1:
        rows = rows[1:]
    a = np.array(rows, float)
    a = a.T if a.shape[0] == 3 and a.shape[1] != 3 else a
    return a / np.linalg.norm(a, axis=1, keepdims=True)


def _angles(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1, 1)))


def split_by_baseline(d1, d2, baseline):
    """Two spheres' directions to the same lamps, their difference split (deg, per lamp) into the part in the
    plane of the spheres' baseline and the ray, positive where the rays converge in front (the only part
    a lamp's parallax gives), and the part across that plane (no lamp position gives it: the two spheres'
    frames disagree). ``baseline``: from the first sphere to the second (any length)."""
    b = np.asarray(baseline, float)
    inplane, across = [], []
    for u, v in zip(d1, d2):
        m = (u + v) / np.linalg.norm(u + v)
        nrm = np.cross(b, m)
        nrm /= np.linalg.norm(nrm)
        e = np.cross(m, nrm)
        dd = v - u
        across.append(math.degrees(dd @ nrm))
        inplane.append(-math.degrees(dd @ e) * np.sign(b @ e))
    return np.array(inplane), np.array(across)


def render_doc(results: dict) -> str:
    """docs/benchmarks.md's real spheres table: one row per capture, its directions against the published ones
    (median / max, deg; bold: within :data:`DOC_BOLD_DEG`), ``note`` in brackets after them.

    Parameters
    ----------
    results : dict
        ``{"rows": [{"name", "label"?, "centre_px", "radius_px", "kind", "median_deg"?, "max_deg"?, "note"?,
        "time_s"}]}`` as docs/benchmarks/spheres_real.json keeps them.
    """
    def deg(v):
        return f"**{v:.2f}**" if v <= DOC_BOLD_DEG else f"{v:.2f}"

    lines = ["| capture | found (centre, radius px) | kind | vs published: median / max | time (s) |",
             "|---|---|---|---|---|"]
    for r in results["rows"]:
        vs = f"{deg(r['median_deg'])} / {deg(r['max_deg'])}" if r.get("median_deg") is not None else ""
        if r.get("note"):
            vs += f" ({r['note']})"
        c = r["centre_px"]
        lines.append(f"| {r.get('label') or r['name']} | ({c[0]:.1f}, {c[1]:.1f}), {r['radius_px']:.1f} | {r['kind']} | "
                     f"{vs} | {r['time_s']:.1f} |")
    return "\n".join(lines) + "\n"


def write_doc_section(rows: list, argv) -> Path:
    """``--doc``: the captures measured replace the kept rows of their names (label and note kept)."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    import benchdoc
    path = benchdoc.json_path(DOC_SECTION, json_dir=benchdoc.JSON_DIR)
    old = json.loads(path.read_text(encoding="utf-8")) if path.is_file() else {"rows": []}
    kept = {r["name"]: r for r in old["rows"]}
    for r in rows:
        before = kept.get(r["name"], {})
        r.update({k: before[k] for k in ("label", "note") if k in before})
    new = {r["name"]: r for r in rows}
    out = [new.pop(r["name"], r) for r in old["rows"]] + list(new.values())
    doc = dict(old, rows=out, argv=list(argv))
    return benchdoc.write_doc(DOC_SECTION, doc, render_doc(doc), source="scripts/benchmark_spheres_real.py")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--capture", action="append", default=[], help="NAME=FOLDER[:LIGHTS]")
    ap.add_argument("--same-lamps", action="append", default=[], help="NAME,NAME")
    ap.add_argument("--crop", action="append", default=[],
                    help="NAME=COL,ROW: where a capture's images were cropped from the frame, rows counted down "
                         "from its top (PSBox's data/ManualData/probes_bbox.txt counts rows up, 991-1990 and "
                         "991-1940: psbox_lightprobe1=0,990 psbox_lightprobe2=2750,1040); with --same-lamps, the "
                         "difference is split along the spheres' baseline")
    ap.add_argument("--pixel-size-um", type=float, default=100.0)
    ap.add_argument("--doc", action="store_true",
                    help="write the captures' rows into docs/benchmarks.md (section spheres_real) and "
                         "docs/benchmarks/spheres_real.json")
    args = ap.parse_args(argv)
    measured = []
    caps = args.capture or [f"psbox_lightprobe2={DATA / 'sphere_mirror_psbox'}:"
                            f"{DATA / 'sphere_mirror_psbox' / 'light_directions.txt'}"]
    dirs, centres = {}, {}
    crops = {n: np.array(v.split(","), float) for n, v in (c.split("=", 1) for c in args.crop)}
    print("| capture | found (centre, radius px) | kind | vs published: median / max (deg) | time (s) |")
    print("|---|---|---|---|---|")
    for spec in caps:
        name, rest = spec.split("=", 1)
        folder, _, lights = rest.partition(":")
        if not Path(folder).is_dir():
            print(f"| {name} | {folder}: not found | | | |")
            continue
        with tempfile.TemporaryDirectory() as tmp:
            t0 = time.perf_counter()
            try:
                COMMANDS["calibrate"]({"spheres": [folder]}, {"pixel_size_um": args.pixel_size_um}, Path(tmp) / "CAL")
            except Exception as e:          # a refusal is a result here
                print(f"| {name} | refused: {e} | | | |")
                continue
            dt = time.perf_counter() - t0
            doc = json.loads((Path(tmp) / "CAL" / "calibration.json").read_text())
        d = np.array([lamp["direction"] for lamp in doc["lamps"]])
        dirs[name] = d
        s = doc["spheres"][0]
        centres[name] = np.array(s["centre_px"][:2], float)
        vs = ""
        row = {"name": name, "centre_px": [float(v) for v in s["centre_px"][:2]], "radius_px": float(s["radius_px"]),
               "kind": s["kind"], "time_s": dt}
        if lights:
            ang = _angles(d, _published(lights))
            vs = f"{np.median(ang):.2f} / {ang.max():.2f}"
            row.update(median_deg=float(np.median(ang)), max_deg=float(ang.max()))
        measured.append(row)
        print(f"| {name} | ({s['centre_px'][0]:.1f}, {s['centre_px'][1]:.1f}), {s['radius_px']:.1f} | {s['kind']} | "
              f"{vs} | {dt:.1f} |")
    for pair in args.same_lamps:
        a, b = pair.split(",")
        if a in dirs and b in dirs:
            ang = _angles(dirs[a], dirs[b])
            print(f"\n{a} against {b} (one capture's two spheres): median {np.median(ang):.2f}, max {ang.max():.2f} deg")
            if a in crops and b in crops:
                (ca, ra), (cb, rb) = centres[a] + crops[a], centres[b] + crops[b]
                inplane, across = split_by_baseline(dirs[a], dirs[b], [cb - ca, ra - rb, 0.0])
                print(f"  in the plane of their baseline (parallax: + converging) {np.round(inplane, 2).tolist()}\n"
                      f"  across it (no lamp position gives it): median {np.median(np.abs(across)):.2f}, "
                      f"max {np.abs(across).max():.2f} deg")
    if args.doc and measured:
        print("wrote", write_doc_section(measured, sys.argv[1:] if argv is None else argv))
    return 0


if __name__ == "__main__":
    sys.exit(main())
