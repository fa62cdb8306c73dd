#!/usr/bin/env python3
"""Normals on real photographs: ``uvps run``'s defaults against plain least squares.

    OMP_NUM_THREADS=1 .venv/bin/python scripts/benchmark_real.py [--data ../shared/data]
        [--diligent DIR [--jpeg]] [--variants]

Two measures, both on real photographs nobody here made:

* **Split-half agreement** on the RTI captures with a light file in ``--data`` (``painted_icon_rti``,
  ``lion_relief_rti``; sRGB JPEGs linearised on reading): the lamps split into the even- and the
  odd-indexed ones, normals solved from each half, the mean / median angle between the halves' normals
  over the pixels both solve. Agreement is precision, not accuracy: a solver that keeps shadowed samples is
  biased the same way in both halves.
* **Ground truth** (``--diligent``: a DiLiGenT ``pmsData`` folder, each object ``<name>PNG/`` with its
  16-bit PNGs, ``light_directions.txt``, ``light_intensities.txt``, ``mask.png`` and ``Normal_gt.mat``): the
  mean angular error against the measured normals inside the mask, every lamp used; with ``--jpeg`` also each
  object encoded as 8-bit sRGB JPEGs (an RTI capture's encoding), to tell the encoding from the surface.

"defaults" is :func:`uvps.core.pipeline.run` with ``RunOptions()`` (what ``uvps run --lights`` does), on
the capture as :func:`uvps.files.io.read_capture` reads it. "plain LS" is least squares on the mean of
R, G and B with every sample (``numpy.linalg.lstsq``, written here independently of the core).
``--variants`` adds the core's solver with each of its sample rules alone (saturation, the dark fraction,
the attached-shadow test) and ``robust=True``, to show which rule costs what.

``--doc`` writes docs/benchmarks.md's table (section ``real``: defaults, plain LS, screened, ``--robust``)
and the rows into docs/benchmarks/real.json; rows this run did not measure (DiLiGenT without ``--diligent``)
are kept from that file's previous run (scripts/benchdoc.py).
"""
import argparse
import json
import sys
import tempfile
from dataclasses import replace
from pathlib import Path

import numpy as np

from uvps.core.pipeline import RunOptions, run
from uvps.core.stereo import EVERY_SAMPLE, solve_normals
from uvps.files.io import read_capture

#: ``../shared/data`` beside the project's checkout (a worktree one level deeper: two levels up)
DEFAULT_DATA = next((p for p in (Path(__file__).resolve().parents[k] / "shared" / "data" for k in (2, 3)) if p.is_dir()),
                    Path(__file__).resolve().parents[2] / "shared" / "data")
RTI = {"painted_icon_rti": ("", "dirs.lp"), "lion_relief_rti": ("jpg", "dirs.lp")}
DOC_SECTION = "real"
#: the document's columns: (heading, method name); the defaults' mean is bold everywhere (the split-half and
#: DiLiGenT targets are about it), ``--robust``'s on ground truth (its target)
DOC_COLUMNS = (("defaults", "defaults"), ("plain LS", "plain LS"), ("screened", "core, all rules (screened)"),
               ("`--robust`", "--robust"))


def angle_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


def plain_ls(images, D, E=None):
    """Least squares on the grey (mean of the channels) intensities, every sample: (M, N, 3) unit normals."""
    K = images.shape[0]
    grey = np.asarray(images, np.float64)
    if grey.ndim == 4:
        grey = grey.mean(axis=-1)
    A = np.asarray(D, float) * (1.0 if E is None else np.asarray(E, float)[:, None])
    b, *_ = np.linalg.lstsq(A, grey.reshape(K, -1), rcond=None)
    n = b.T.reshape(grey.shape[1:] + (3,))
    with np.errstate(invalid="ignore", divide="ignore"):
        return n / np.linalg.norm(n, axis=-1, keepdims=True)


def subset(cap, idx):
    pick = lambda a: None if a is None else np.asarray(a)[idx]   # noqa: E731
    return replace(cap, images=np.stack([np.asarray(cap.images[int(k)]) for k in idx]),
                   files=[cap.files[int(k)] for k in idx], light_directions=pick(cap.light_directions),
                   light_positions_mm=pick(cap.light_positions_mm), light_intensities=pick(cap.light_intensities))


def methods(variants):
    """name -> normals_of(capture): (M, N, 3)."""
    def defaults(cap, **opts):
        return run(cap, RunOptions(**opts), stages=("normals",)).stereo.normals

    def core(cap, **kw):
        from uvps.core.irradiance import LightModel
        model = LightModel.from_directions(cap.light_directions, cap.light_intensities)
        imgs = np.asarray(cap.images, np.float32)
        return solve_normals(imgs, model, pixel_size_um=cap.pixel_size_um, mask=cap.mask, **kw).normals

    out = {"defaults": defaults,
           "plain LS": lambda cap: plain_ls(cap.images, cap.light_directions, cap.light_intensities)}
    if variants:
        none = dict(EVERY_SAMPLE)
        out.update({
            "core, no rule": lambda cap: core(cap, **none),
            "core, 0-count samples out": lambda cap: core(cap, **{**none, "dark_fraction": 0.0}),
            "core, saturation only": lambda cap: core(cap, **{**none, "saturation": cap.saturation}),
            "core, dark 2 % only": lambda cap: core(cap, **{**none, "dark_fraction": 0.02}),
            "core, shadow test only": lambda cap: core(cap, **{**none, "shadow_cos": 0.05}),
            "core, all rules (screened)": lambda cap: core(cap, saturation=cap.saturation),
            "--robust": lambda cap: defaults(cap, robust=True),
        })
    return out


def split_half(cap, fns):
    K = cap.images.shape[0]
    halves = [subset(cap, np.arange(h, K, 2)) for h in (0, 1)]
    row = {}
    for name, fn in fns.items():
        a, b = (fn(h) for h in halves)
        ok = np.isfinite(a).all(-1) & np.isfinite(b).all(-1)
        if cap.mask is not None:
            ok &= cap.mask
        ang = angle_deg(a[ok], b[ok])
        row[name] = (float(ang.mean()), float(np.median(ang)), int(ok.sum()))
    return row


def diligent_capture(obj: Path, tmp: Path):
    """A DiLiGenT object as uvps reads it: its 16-bit PNGs, an ``.lp`` with the directions in uvps's frame and
    each lamp's intensity (the mean of its R, G, B intensities), its mask; and the measured normals."""
    from scipy.io import loadmat

    names = (obj / "filenames.txt").read_text().split()
    D = np.loadtxt(obj / "light_directions.txt")
    E = np.loadtxt(obj / "light_intensities.txt").mean(axis=1)
    # DiLiGenT's frame: x right, y up, z toward the camera (as uvps's), checked by plain LS on the ball
    lp = tmp / f"{obj.name}.lp"
    lp.write_text(f"{len(names)}\n" + "".join(f"{n} {d[0]:.6f} {d[1]:.6f} {d[2]:.6f} {e:.6f}\n"
                                              for n, d, e in zip(names, D, E)))
    cap = read_capture([str(obj / n) for n in names], lights=str(lp), mask=str(obj / "mask.png"),
                       pixel_size_um=100.0)
    gt = loadmat(obj / "Normal_gt.mat")["Normal_gt"].astype(np.float64)
    return cap, gt


def as_jpeg(obj: Path, tmp: Path, quality=90) -> Path:
    """The object's images encoded as an RTI capture's are: 8-bit sRGB JPEGs (OpenCV, ``quality``), 16-bit
    counts scaled by 1/65535 (no gain), with its mask, light files and normals beside them."""
    import shutil
    import cv2

    out = tmp / f"{obj.name}"
    out.mkdir()
    names = (obj / "filenames.txt").read_text().split()
    for n in names:
        lin = np.clip(cv2.imread(str(obj / n), cv2.IMREAD_UNCHANGED).astype(np.float64) / 65535.0, 0, 1)
        enc = np.where(lin <= 0.0031308, 12.92 * lin, 1.055 * lin ** (1 / 2.4) - 0.055)
        cv2.imwrite(str(out / (Path(n).stem + ".jpg")), np.round(255 * enc).astype(np.uint8),
                    [cv2.IMWRITE_JPEG_QUALITY, quality])
    (out / "filenames.txt").write_text("\n".join(Path(n).stem + ".jpg" for n in names) + "\n")
    for f in ("light_directions.txt", "light_intensities.txt", "mask.png", "Normal_gt.mat"):
        shutil.copy(obj / f, out / f)
    return out


def ground_truth(cap, gt, fns):
    row = {}
    for name, fn in fns.items():
        n = fn(cap)
        ok = cap.mask & np.isfinite(n).all(-1)
        ang = angle_deg(n[ok], gt[ok])
        row[name] = (float(ang.mean()), float(np.median(ang)), int(ok.sum()), int(cap.mask.sum()))
    return row


def _label(r: dict) -> str:
    if r["kind"] == "halves":
        return f"{r['capture']} ({r['size'][0]} x {r['size'][1]}), halves"
    jpeg = " as JPEG (`--jpeg`, quality 90)" if r.get("jpeg") else ""
    return f"DiLiGenT {r['capture']}{jpeg}, ground truth"


def render_doc(results: dict) -> str:
    """docs/benchmarks.md's table: mean / median angle (deg) per capture and method, '-' where not measured.

    Parameters
    ----------
    results : dict
        ``{"rows": [{"capture", "kind" ("halves" or "ground truth"), "size" (W, H), "jpeg", "lamps",
        "methods": {name: [mean, median, pixels, ...]}}, ...]}`` as docs/benchmarks/real.json keeps them.
    """
    lines = ["| capture | lamps | " + " | ".join(h for h, _ in DOC_COLUMNS) + " |",
             "|---|---|" + "---|" * len(DOC_COLUMNS)]
    for r in results["rows"]:
        cells = []
        for _, name in DOC_COLUMNS:
            v = r["methods"].get(name)
            bold = name == "defaults" or (name == "--robust" and r["kind"] == "ground truth")
            cells.append("-" if v is None else (f"**{v[0]:.2f}**" if bold else f"{v[0]:.2f}") + f" / {v[1]:.2f}")
        lines.append(f"| {_label(r)} | {r['lamps']} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _row_key(r: dict):
    return (r["kind"] != "halves", list(RTI).index(r["capture"]) if r["capture"] in RTI else 0, r["capture"],
            bool(r.get("jpeg")))


def write_doc_section(rows: list, argv: list) -> None:
    """``--doc``: this run's rows over the previous run's (same capture and kind), into the JSON and the table."""
    import benchdoc
    old = benchdoc.json_path(DOC_SECTION, json_dir=benchdoc.JSON_DIR)
    kept = json.loads(old.read_text(encoding="utf-8"))["rows"] if old.is_file() else []
    new = {_row_key(r): r for r in kept}
    new.update({_row_key(r): r for r in rows})
    results = {"argv": argv, "rows": [new[k] for k in sorted(new)]}
    print("wrote", benchdoc.write_doc(DOC_SECTION, results, render_doc(results), source="scripts/benchmark_real.py"))


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", default=str(DEFAULT_DATA))
    ap.add_argument("--diligent", help="a DiLiGenT pmsData folder (objects <name>PNG/ with Normal_gt.mat)")
    ap.add_argument("--variants", action="store_true", help="also the core's sample rules one by one")
    ap.add_argument("--jpeg", action="store_true", help="DiLiGenT's objects also encoded as 8-bit sRGB JPEGs")
    ap.add_argument("--doc", action="store_true",
                    help="write the table into docs/benchmarks.md (section real) and docs/benchmarks/real.json")
    args = ap.parse_args(argv)
    rows = []
    fns = methods(args.variants)
    data = Path(args.data)
    names = list(fns)
    print("| capture | lamps per half | " + " | ".join(names) + " |")
    print("|---|---|" + "---|" * len(names))
    for cap_name, (sub, lp) in RTI.items():
        folder = data / cap_name
        if not folder.is_dir():
            print(f"| {cap_name} | absent | " + " | " * len(names))
            continue
        cap = read_capture(str(folder / sub) if sub else str(folder), lights=str(folder / lp), pixel_size_um=100.0)
        row = split_half(cap, fns)
        rows.append({"capture": cap_name, "kind": "halves", "size": [cap.images.shape[2], cap.images.shape[1]],
                     "lamps": cap.images.shape[0] // 2, "methods": row})
        print(f"| {cap_name} | {cap.images.shape[0] // 2} | "
              + " | ".join(f"{m:.2f} / {md:.2f}" for m, md, _ in row.values()) + " |", flush=True)
    if args.diligent:
        print()
        print("| DiLiGenT object | lamps | " + " | ".join(names) + " |")
        print("|---|---|" + "---|" * len(names))
        with tempfile.TemporaryDirectory() as tmp:
            for obj in sorted(Path(args.diligent).glob("*PNG")):
                if not (obj / "Normal_gt.mat").is_file():
                    continue
                for label, src in [("", obj)] + ([(" as JPEG", None)] if args.jpeg else []):
                    src = src or as_jpeg(obj, Path(tmp))
                    cap, gt = diligent_capture(src, Path(tmp))
                    row = ground_truth(cap, gt, fns)
                    rows.append({"capture": obj.name[:-3], "kind": "ground truth", "jpeg": bool(label),
                                 "size": [cap.images.shape[2], cap.images.shape[1]], "lamps": cap.images.shape[0],
                                 "methods": row})
                    print(f"| {obj.name[:-3]}{label} | {cap.images.shape[0]} | "
                          + " | ".join(f"{m:.2f} / {md:.2f}" for m, md, _, _ in row.values()) + " |", flush=True)
    if args.doc:
        write_doc_section(rows, list(sys.argv[1:] if argv is None else argv))
    return 0


if __name__ == "__main__":
    sys.exit(main())
