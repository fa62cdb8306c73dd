"""The words and numbers of the run report: its summary, tables, methods appendix and provenance.

:mod:`uvps.report.page` draws the figures and assembles ``report.html``; this module turns ``run.json``,
``lights.json``, the protrusion table and the per-area statistics into what a conservator reads
and cites. Every number goes through one of the formatters below, which round it to what the
measurement holds (a count is exact; a density of 9 protrusions in 0.22 cm^2 is 41 +- 14 per cm^2,
so "41", not "41.06438896"). Nothing here computes a result: it only reads and words them.
"""
from __future__ import annotations

import html
import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np

from ..core.detect import REJECTION_WORDS

e = html.escape

#: How the lamps were known (run.json ``relief.lamps``, else ``diagnostics.lights.source``).
LAMP_ROUTES = {
    "calibration": "from a calibration folder (uvps calibrate)",
    "positions": "from measured lamp positions",
    "directions": "from given lamp directions (far lights: no fall-off across the field)",
    "estimated": "estimated from the images alone (no reference sphere, no measured positions)",
}

#: How a calibration folder measured the lamps (``calibration.json`` ``route``).
CALIBRATION_ROUTES = {"spheres": "reference spheres photographed under each lamp",
                      "positions": "measured lamp positions", "dome": "the dome's known geometry",
                      "lp": "a light-position (.lp) file"}

#: The protrusion table's ``source`` values, in words.
SOURCE_WORDS = {"albedo+height": "by fluorescence and relief", "height": "by relief alone",
                "albedo": "by fluorescence alone", "wand": "outlined with the wand (manual method)",
                "manual": "outlined with the wand (manual method)"}


# ---------------------------------------------------------------------------------------------
# numbers


def sig(x, n: int = 2) -> str:
    """``x`` to ``n`` significant figures, in plain notation (``sig(41.064) == "41"``,
    ``sig(0.21917, 2) == "0.22"``, ``sig(177.9, 2) == "180"``); "" for NaN/None."""
    if x is None:
        return ""
    x = float(x)
    if not math.isfinite(x):
        return ""
    if x == 0:
        return "0"
    d = n - 1 - int(math.floor(math.log10(abs(x))))
    r = round(x, d)
    if r != 0 and int(math.floor(math.log10(abs(r)))) > int(math.floor(math.log10(abs(x)))):
        d -= 1          # 9.96 -> 10, not 10.0
    return f"{r:.{d}f}" if d > 0 else f"{int(round(r)):d}"


def fixed(x, decimals: int = 1) -> str:
    """``x`` with a fixed number of decimals; "" for NaN/None."""
    if x is None or not math.isfinite(float(x)):
        return ""
    return f"{float(x):.{decimals}f}"


def density(x) -> str:
    """A density per cm^2: two significant figures (a count's Poisson error is larger)."""
    return sig(x, 2)


def density_pm(value, se) -> str:
    """A density and its standard error, both to the same decimal place (``"45 \u00b1 9"``,
    ``"3.2 \u00b1 2.2"``): whole numbers from 10 per cm^2, else one decimal (two below 1)."""
    v = float(value)
    d = 0 if abs(v) >= 10 else 1 if abs(v) >= 1 or v == 0 else 2
    return f"{v:.{d}f} \u00b1 {float(se):.{d}f}"


def plain(x) -> str:
    """A parameter as given (``30.0`` -> ``"30"``, ``0.5`` -> ``"0.5"``)."""
    return "" if x is None else f"{float(x):g}"


def cm2(x) -> str:
    """An area in cm^2 (counted in pixels, so three significant figures hold)."""
    return sig(x, 3)


def width_quantum(pixel_size_um: Optional[float]) -> float:
    """The step widths are rounded to: the power of ten at or below the pixel size (30 um -> 10)."""
    if not pixel_size_um or not math.isfinite(pixel_size_um) or pixel_size_um <= 0:
        return 1.0
    return 10.0 ** math.floor(math.log10(pixel_size_um))


def width(x, pixel_size_um: Optional[float]) -> str:
    """A width in um, rounded to :func:`width_quantum` (an outline is good to about a pixel)."""
    if x is None or not math.isfinite(float(x)):
        return ""
    q = width_quantum(pixel_size_um)
    v = round(float(x) / q) * q
    return f"{v:.0f}" if q >= 1 else sig(v, 3)


def height(x) -> str:
    """A height in um: two significant figures (the heights' scale is rarely known better than a
    few %), not finer than 0.1 um."""
    if x is None or not math.isfinite(float(x)):
        return ""
    x = float(x)
    return fixed(x, 1) if abs(x) < 10 else sig(x, 2)


def percent(fraction) -> str:
    """A fraction as a percentage: whole percent, or one significant figure below 1 %."""
    if fraction is None or not math.isfinite(float(fraction)):
        return ""
    p = 100.0 * float(fraction)
    return f"{p:.0f} %" if abs(p) >= 1 else f"{sig(p, 1)} %"


def poisson_se(count: int, area_cm2: float) -> float:
    """Standard error of a density from its count (Poisson: sqrt(n) / area; 1 / area for n = 0)."""
    return math.sqrt(max(count, 1)) / area_cm2 if area_cm2 > 0 else float("nan")


def plural(n: int, word: str, words: Optional[str] = None) -> str:
    return f"{n} {word if n == 1 else (words or word + 's')}"


# ---------------------------------------------------------------------------------------------
# what the run folder says


@dataclass
class Facts:
    """What the report says about a run, gathered once from its files (missing parts None)."""

    run: dict = field(default_factory=dict)
    lights: dict = field(default_factory=dict)
    pixel_size_um: Optional[float] = None
    shape: Optional[tuple] = None
    relief: dict = field(default_factory=dict)

    @property
    def params(self) -> dict:
        p = self.run.get("params")
        return p if isinstance(p, dict) else {}

    @property
    def diagnostics(self) -> dict:
        d = self.run.get("diagnostics")
        return d if isinstance(d, dict) else {}

    @property
    def relative(self) -> bool:
        """True when the heights' scale is not pinned (contract A: ``relief.scale == "relative"``)."""
        return str(self.relief.get("scale", "absolute")) == "relative"

    @property
    def n_images(self) -> Optional[int]:
        n = (self.diagnostics.get("lights") or {}).get("n_lights")
        if n is None and self.lights.get("lights"):
            n = len(self.lights["lights"])
        return int(n) if n is not None else None

    @property
    def field_mm(self) -> Optional[tuple]:
        if self.shape is None or not self.pixel_size_um or not math.isfinite(self.pixel_size_um):
            return None
        m, n = self.shape[:2]
        return n * self.pixel_size_um / 1000.0, m * self.pixel_size_um / 1000.0

    @property
    def lamp_route(self) -> str:
        """``calibration``, ``positions``, ``directions``, ``estimated`` or "" (unknown)."""
        route = self.relief.get("lamps") or (self.diagnostics.get("lights") or {}).get("source") \
            or self.lights.get("source") or ""
        if self.params.get("calibration"):
            route = "calibration"
        return str(route)


def facts_of(run: Optional[dict], lights: Optional[dict], *, pixel_size_um, shape) -> Facts:
    """The :class:`Facts` of a run folder (``run.json`` and ``lights.json`` as read, or None)."""
    run = run if isinstance(run, dict) else {}
    relief = run.get("relief") if isinstance(run.get("relief"), dict) else {}
    px = float(pixel_size_um) if pixel_size_um is not None else None
    return Facts(run, lights if isinstance(lights, dict) else {}, px,
                 tuple(shape) if shape is not None else None, relief)


# ---------------------------------------------------------------------------------------------
# the summary


def _capture_sentence(f: Facts) -> str:
    bits = []
    n = f.n_images
    if n:
        bits.append(f"{n} UV images, one per lamp position")
    if f.shape is not None:
        m, nn = f.shape[:2]
        bits.append(f"{nn} \u00d7 {m} pixels")
    if f.pixel_size_um and math.isfinite(f.pixel_size_um):
        bits.append(f"{plain(f.pixel_size_um)} \u00b5m per pixel")
    s = ", ".join(bits) if bits else "an unknown capture"
    fm = f.field_mm
    if fm is not None:
        s += (f": a field of {fixed(fm[0], 1)} \u00d7 {fixed(fm[1], 1)} mm "
              f"({cm2(fm[0] * fm[1] / 100.0)} cm\u00b2)")
    return f"<p><b>Captured:</b> {s}.</p>"


def _count_sentence(table, stats, f: Facts, table_name: str) -> str:
    if table is None:
        return ("<p><b>Protrusions:</b> not counted (no protrusion table: run with "
                "<code>--regions auto</code> or <code>--detect</code>, or the <code>detect</code> "
                "or <code>wand</code> command).</p>")
    n = len(table["width_um"])
    src, counts = np.unique(np.asarray(table["source"], dtype=str), return_counts=True)
    how = "; ".join(f"{c} {SOURCE_WORDS.get(s, s or 'source not recorded')}"
                    for s, c in zip(src, counts))
    manual = all(s in ("wand", "manual") for s in src) and n
    s = f"<b class='big'>{plural(n, 'protrusion')}</b> "
    s += ("outlined by hand (the wand)" if manual else "found by automated detection")
    if n and how and not manual:
        s += f" ({e(how)})"
    craters = int(np.sum(np.asarray(table["crater"]) > 0))
    w = np.asarray(table["width_um"], float)
    if n:
        s += f", {plural(craters, 'with a crater', 'with a crater')}" if craters else ""
        s += (f"; widths {width(np.nanmin(w), f.pixel_size_um)}\u2013"
              f"{width(np.nanmax(w), f.pixel_size_um)} \u00b5m (median "
              f"{width(np.nanmedian(w), f.pixel_size_um)} \u00b5m)")
    s += f" <span class='src'>({e(table_name)})</span>."
    if stats is not None:
        total = stats.rows[-1]
        areas = [r for r in stats.rows if r.label != "all"]
        s += (f" Overall <b>{density(total.density_per_cm2)} per cm\u00b2</b> over "
              f"{cm2(total.area_cm2)} cm\u00b2")
        s += f" in {plural(len(areas), 'colour area')}." if len(areas) > 1 else "."
    return f"<p><b>Protrusions:</b> {s}</p>"


def _where_sentence(stats, names_editable: bool) -> str:
    if stats is None:
        return ""
    areas = [r for r in stats.rows if r.label != "all" and r.area_cm2 > 0]
    if len(areas) < 2:
        return ""
    by = sorted(areas, key=lambda r: -r.density_per_cm2)
    top = [r for r in by if r.count > 0][:min(3, len(areas) - 1)]
    if not top:
        return "<p><b>Where:</b> no protrusion in any colour area.</p>"

    def one(r):
        return (f"<b>{e(r.name)}</b> ({density_pm(r.density_per_cm2, poisson_se(r.count, r.area_cm2))}"
                " per cm\u00b2)")

    s = "Densest: " + ", ".join(one(r) for r in top)
    empty = [r for r in areas if r.count == 0]
    if empty:
        names = [f"<b>{e(r.name)}</b>" for r in empty]
        s += "; none in " + (", ".join(names) if len(names) <= 4
                             else ", ".join(names[:3]) + f" and {len(names) - 3} more areas")
    elif by[-1] not in top:
        s += "; least dense: " + one(by[-1])
    s += ". (\u00b1: standard error from the count.)"
    return f"<p><b>Where:</b> {s}</p>"


def _lamps_item(f: Facts) -> str:
    route = f.lamp_route
    words = LAMP_ROUTES.get(route, "not recorded")
    given = f.params.get("calibration") or f.params.get("lights")
    s = f"Lamps: {words}"
    if given and route != "estimated":
        s += f" (<code>{e(Path(str(given)).name)}</code>"
        cal_route = _calibration_route(f.params.get("calibration"))
        s += f": {e(CALIBRATION_ROUTES.get(cal_route, cal_route))})" if cal_route else ")"
    n_l = len(f.lights.get("lights") or [])
    u = (f.diagnostics.get("lights") or {}).get("direction_uncertainty_deg_max")
    if u is not None:
        s += f"; each lamp's direction within {sig(u, 2)}\u00b0 (standard uncertainty, largest of {n_l})"
    return s + "."


def _calibration_route(cal) -> str:
    """The ``route`` of a calibration folder's ``calibration.json`` ("" when it cannot be read:
    the folder may have moved since the run)."""
    if not cal:
        return ""
    try:
        info = json.loads((Path(str(cal)) / "calibration.json").read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return ""
    return str(info.get("route") or "") if isinstance(info, dict) else ""


def _heights_item(f: Facts) -> str:
    if f.relative:
        reason = f.relief.get("reason") or "the lamps' elevation is not pinned by a known geometry"
        return (f"Heights: <b>relative only</b>, no micrometres: {e(str(reason))} Shapes, widths and "
                "counts hold; give a calibration (<code>uvps calibrate</code>, "
                "<code>--calibration</code>) or measured lamp positions (<code>--lights</code>) for "
                "heights in \u00b5m.")
    lights_d = f.diagnostics.get("lights") or {}
    hu = lights_d.get("height_uncertainty_relative")
    s = "Heights: "
    if hu is not None:
        s += (f"scale uncertain by \u00b1{percent(hu)} (standard uncertainty, from the lamps' "
              "estimate)")
    elif f.lamp_route in ("positions", "calibration", "directions"):
        s += "scale set by the given lamps (its uncertainty is that of their measurement)"
    else:
        s += "scale uncertainty not recorded"
    noise = (f.diagnostics.get("detect") or {}).get("noise_um")
    if noise is not None:
        s += f"; height noise {sig(noise, 1)} \u00b5m"
    return s + "." + level_sentence(f)


def level_sentence(f: Facts) -> str:
    """What was removed from the heights (run.json ``level``, :mod:`uvps.core.level`) and why: a mean
    bias of the normals of d deg is a slope of tan(d), 17.5 um per mm per degree, a ramp across the
    field larger than the relief; "" for a run that records none."""
    lev = f.run.get("level")
    if not isinstance(lev, dict) or lev.get("slope_x_um_per_mm") is None:
        return ""
    sx, sy = float(lev["slope_x_um_per_mm"]), float(lev.get("slope_y_um_per_mm") or 0.0)
    slope = math.hypot(sx, sy)
    tilt = math.degrees(math.atan(slope / 1000.0))
    unit = "\u00b5m/mm" if not f.relative else "units per mm"
    plane = (f"slope {sx:+.2f} {unit} toward the right and {sy:+.2f} {unit} upward, a tilt of "
             f"{sig(tilt, 2) if tilt >= 0.01 else fixed(tilt, 3)}\u00b0")
    fm = f.field_mm
    ramp = (f", {height(slope * max(fm))} \u00b5m across this {fixed(max(fm), 0)} mm field"
            if fm is not None and not f.relative else "")
    bias = ("A mean bias of the normals of d\u00b0 (the lamps' directions off by that much on average) tilts "
            "the heights by tan(d), 17.5 \u00b5m per mm for each degree; a calibration leaves a few tenths of a "
            "degree, enough to ramp the heights across the field more than the paint's relief rises")
    why = (bias + ", so the plane is removed (as surface metrology removes the form, ISO 25178) and the relief "
           "shows; the painting's own tilt goes with it.")
    method = lev.get("method")
    if method == "plane":
        return (f" <b>Levelled</b>: the best plane removed ({plane}{ramp}); the heights as integrated are "
                f"<code>depth.tif</code> plus that plane (run.json <code>level</code>). {why}")
    if method == "form":
        rms = lev.get("removed_rms_um")
        return (f" <b>Levelled</b>: a smooth form (2-D Legendre polynomial of degree {e(str(lev.get('degree')))}) "
                f"removed, {height(rms) if rms is not None else '?'} {unit.split('/')[0]} rms: the canvas's "
                f"bow with it; its plane {plane}{ramp}. The heights as integrated are <code>depth.tif</code> "
                f"plus that form (run.json <code>level</code>). {why}")
    return (f" <b>Not levelled</b> (<code>--level none</code>): the heights hold a plane ({plane}{ramp}). "
            f"{bias} (<code>--level plane</code> removes it).")


def _excluded_item(f: Facts, stats, table) -> str:
    det = f.diagnostics.get("detect") or {}
    rej = {k: int(v) for k, v in (det.get("rejected") or {}).items() if int(v) > 0}
    parts = []
    if rej:
        kept = int(det.get("n_protrusions", len(table["width_um"]) if table is not None else 0))
        n_rej = sum(rej.values())
        why = ", ".join(f"{v} {REJECTION_WORDS.get(k, k)}"
                        for k, v in sorted(rej.items(), key=lambda kv: -kv[1]))
        parts.append(f"{n_rej} of {n_rej + kept} candidate features rejected ({why})")
    n_invalid = (f.diagnostics.get("normals") or {}).get("n_invalid")
    if n_invalid and f.shape is not None:
        parts.append(f"{n_invalid} pixels ({percent(n_invalid / (f.shape[0] * f.shape[1]))}) "
                     "lit by fewer than 3 lamps: no shape there")
    if stats is not None and stats.outside:
        parts.append(f"{plural(stats.outside, 'protrusion')} outside every colour area, not in "
                     "the densities")
    if f.params.get("mask"):
        parts.append(f"pixels outside the mask <code>{e(Path(str(f.params['mask'])).name)}</code>")
    if not parts:
        return "Excluded: nothing."
    return "Excluded: " + "; ".join(parts) + "."


def summary_html(f: Facts, table, stats, warnings: list, *, table_name: str,
                 definition: str) -> str:
    """The report's first section: what was captured, how many protrusions, where, how sure."""
    out = ["<section id='summary'><h2>Summary</h2>", _capture_sentence(f),
           _count_sentence(table, stats, f, table_name), _where_sentence(stats, True)]
    sure = [_lamps_item(f), _heights_item(f), _excluded_item(f, stats, table)]
    if warnings:
        sure.append("<span class='warn'>Warnings:</span><ul>"
                    + "".join(f"<li class='warn'>{e(str(w))}</li>" for w in warnings) + "</ul>")
    else:
        sure.append("Warnings: none.")
    out.append("<p><b>How sure:</b></p><ul class='sure'>"
               + "".join(f"<li>{s}</li>" for s in sure) + "</ul>")
    if definition:
        out.append(f"<p class='def'><b>What counts as a protrusion:</b> {definition}</p>")
    out.append("</section>")
    return "\n".join(out)


def protrusion_definition(f: Facts, table, detection_defaults: dict) -> str:
    """One paragraph: what the count counts (the detection's rules with this run's numbers)."""
    if table is None:
        return ""
    src = set(np.asarray(table["source"], dtype=str))
    if src and src <= {"wand", "manual"}:
        tol = f.params.get("tolerance")
        return ("each outline grown with the wand from a point the user clicked, over the "
                "albedo" + (f" (tolerance {e(str(tol))})" if tol is not None else "")
                + "; its width is the diameter of the circle of the same area.")
    p = dict(detection_defaults)
    p.update({k: v for k, v in f.params.items() if k in p and v is not None})
    noise = (f.diagnostics.get("detect") or {}).get("noise_um")
    thresh = (f"max({plain(p['min_dynamic_um'])} \u00b5m, {plain(p['dynamic_k'])} \u00d7 the "
              "height noise")
    thresh += f" of {sig(noise, 1)} \u00b5m)" if noise is not None else ")"
    if f.relative:
        thresh = "the relief threshold (in the run's relative height units)"
    return (f"a compact raised feature (one summit, a crater's rim, or a plateau) "
            f"{plain(p['min_width_um'])}\u2013{plain(p['max_width_um'])} \u00b5m wide, standing at "
            f"least {thresh} above the paint around it, and not rejected as a brush stroke, crack, "
            "weave or bare primer (the rules under <i>Excluded</i>). Bright fluorescence adds "
            "candidates and outline but is not required. The width is the diameter of the circle "
            "of the same area; the height is the summit above a plane through the paint around it.")


# ---------------------------------------------------------------------------------------------
# tables


def table_html(header, rows, *, cls: str = "", caption: str = "") -> str:
    """A table whose cells are already text (escaped here unless wrapped in :class:`Raw`)."""
    head = "".join(f"<th>{h if isinstance(h, Raw) else e(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{c if isinstance(c, Raw) else e(str(c))}</td>"
                                    for c in row) + "</tr>" for row in rows)
    cap = f"<caption>{caption}</caption>" if caption else ""
    return (f"<table class='{cls}'>{cap}<thead><tr>{head}</tr></thead>"
            f"<tbody>{body}</tbody></table>")


class Raw(str):
    """HTML that :func:`table_html` puts in as it is."""


def swatch(rgb) -> Raw:
    if rgb is None:
        return Raw("")
    r, g, b = (int(round(255 * float(np.clip(c, 0, 1)))) for c in rgb[:3])
    return Raw(f"<span class='sw' style='background:#{r:02x}{g:02x}{b:02x}'></span>")


def area_table_html(stats, colours: Optional[dict]) -> str:
    """Table 1: one row per colour area: its size, count and density with its standard error."""
    rows = []
    for r in stats.rows:
        total = r.label == "all"
        name = Raw(("<b>all areas</b>" if total else
                    swatch((colours or {}).get(r.label)) + e(str(r.name))))
        rows.append([name, cm2(r.area_cm2), str(r.count),
                     density_pm(r.density_per_cm2, poisson_se(r.count, r.area_cm2))])
    header = ["Colour area", Raw("Area (cm\u00b2)"), "Protrusions",
              Raw("Density (per cm\u00b2, \u00b1 standard error)")]
    return table_html(header, rows, cls="num")


def width_table_html(stats, max_cols: int = 8) -> str:
    """Table 2: protrusions per cm^2 by width bin per area (the numbers of the paper's Fig. 4a);
    bins past ``max_cols`` are merged into one "and wider" column."""
    edges = np.asarray(stats.edges_um, float)
    nb = len(edges) - 1
    keep = min(nb, max_cols)
    heads = []
    for j in range(keep):
        lo, hi = edges[j], edges[j + 1]
        if j == keep - 1 and keep < nb or not math.isfinite(hi):
            heads.append(f"\u2265 {lo:g}")
        else:
            heads.append(f"{lo:g}\u2013{hi:g}")
    rows = []
    for r in stats.rows:
        d = list(r.densities[:keep])
        c = list(r.counts[:keep])
        if keep < nb:
            d[-1] = float(np.sum(r.densities[keep - 1:]))
            c[-1] = int(np.sum(r.counts[keep - 1:]))
        name = Raw("<b>all areas</b>" if r.label == "all" else e(str(r.name)))
        rows.append([name] + [f"{density(v)} ({n})" if n else "\u2013" for v, n in zip(d, c)])
    header = ["Colour area"] + [Raw(h + " \u00b5m") for h in heads]
    return table_html(header, rows, cls="num")


def largest_table_html(table, f: Facts, area_names: dict, n: int = 10) -> str:
    """Table 3: the ``n`` widest protrusions with where they are (mm from the top-left corner,
    as ImageJ shows a calibrated image), width, height and crater."""
    w = np.nan_to_num(np.asarray(table["width_um"], float), nan=-1.0)
    order = np.argsort(-w, kind="stable")[:n]
    px = f.pixel_size_um if f.pixel_size_um and math.isfinite(f.pixel_size_um) else None
    heights = None if f.relative else table.get("height_um")
    rows = []
    for i in order:
        row = [str(table["id"][i]), str(area_names.get(int(table["region"][i]), "\u2013"))]
        if px:
            row += [fixed(float(table["x_px"][i]) * px / 1000, 2),
                    fixed(float(table["y_px"][i]) * px / 1000, 2)]
        else:
            row += [fixed(table["x_px"][i], 0), fixed(table["y_px"][i], 0)]
        row.append(width(table["width_um"][i], px))
        if heights is not None:
            row.append(height(heights[i]))
        row.append("yes" if int(table["crater"][i]) else "")
        rows.append(row)
    unit = "mm" if px else "px"
    header = ["No.", "Colour area", f"x ({unit})", f"y ({unit})", Raw("Width (\u00b5m)")]
    if heights is not None:
        header.append(Raw("Height (\u00b5m)"))
    header.append("Crater")
    return table_html(header, rows, cls="num lt")


# ---------------------------------------------------------------------------------------------
# appendix: methods and parameters in words; provenance


def _capture_method(p: dict, d: dict) -> str:
    """Appendix A's first item: how the images were read and what was subtracted."""
    lin = p.get("linearize")
    bit = p.get("bit_depth")
    cap = "Images read as linear signal"
    if bit:
        cap += f" ({e(str(bit))})"
    if lin not in (None, "auto", "none", False):
        cap += f", linearised from {e(str(lin))}"
    if p.get("black_level") is not None:
        cap += f"; the camera's black level {e(str(p['black_level']))} counts subtracted"
    if p.get("dark"):
        cap += f"; the dark frame <code>{e(Path(str(p['dark'])).name)}</code> subtracted"
    add = d.get("additive") or {}
    if add.get("source") == "estimated":
        frac = add.get("fraction_of_median_signal")
        cap += ("; an additive term (stray light, black level) measured from the images"
                + (f" at {percent(frac)} of the median signal" if frac is not None else "")
                + (", subtracted" if add.get("used") else ", not significant, not subtracted"))
    return cap + "."


def methods_html(f: Facts, n_areas: Optional[int], region_source: str) -> str:
    """Appendix A: how the run was made, in words, with the parameters that matter."""
    p, d = f.params, f.diagnostics
    items = [_capture_method(p, d)]
    route = f.lamp_route
    lam = f"Lamps {LAMP_ROUTES.get(route, 'of an unrecorded source')}"
    if route == "estimated":
        lam += (": the fall-off of each image fitted by a 2-D Legendre polynomial of degree "
                f"{e(str(p.get('degree', '?')))} (paper Fig. 1c), the lamps' azimuths from it "
                "(Fig. 1d), then every lamp's position and intensity refined by the photometric "
                "residual (Eq. 2)")
        zs = [float(x["position_mm"][2]) for x in f.lights.get("lights") or []
              if x.get("position_mm") is not None]
        if zs:
            lam += (f"; they came out {sig(min(zs), 2)}\u2013{sig(max(zs), 2)} mm above the "
                    "canvas")
    beams = p.get("lamp_beams")
    if beams in (True, "all"):
        lam += "; each lamp's drop-off beyond the point-light model divided out (the canvas's bow with it)"
    elif beams == "auto" and f.lights.get("lights") and any(x.get("position_mm") for x in f.lights["lights"]):
        lam += ("; each lamp's drop-off beyond the point-light model divided out, but for what a tilt of the "
                "canvas explains (its bow kept)")
    items.append(lam + ".")
    samples = (d.get("normals") or {}).get("samples")
    kept = ("every sample kept, as plain least squares" if samples == "all"
            else "shadowed and saturated samples left out")
    why = (d.get("normals") or {}).get("samples_reason")
    items.append("Normals and albedo by least squares at every pixel over the lamps lighting it "
                 + (f"(rank-trimmed: each pixel's darkest and brightest samples left out; {kept})"
                    if p.get("robust") else f"({kept})")
                 + "; the albedo is the fluorescence with the shading removed."
                 + (f" Samples: {e(why)}." if why else ""))
    integ = {"fc": "Frankot\u2013Chellappa (Fourier, mirrored borders)",
             "dct": "DCT Poisson (Neumann borders)"}.get(str(p.get("integration")),
                                                         str(p.get("integration", "?")))
    lev = f.run.get("level") if isinstance(f.run.get("level"), dict) else {}
    levelled = {"plane": "; the best plane (robust least squares over the valid pixels) removed",
                "form": f"; a 2-D Legendre form of degree {e(str(lev.get('degree')))} (robust least squares) "
                        "removed",
                "none": "; not levelled"}.get(str(lev.get("method")), "")
    items.append(f"Height by integrating the normals: {e(integ)}{levelled}; the median height is set to 0"
                 + (", relative units" if f.relative else ", in \u00b5m") + ".")
    if n_areas is not None:
        items.append(f"Colour areas: {n_areas}, {e(region_source)}.")
    if d.get("detect") or f.params.get("regions") or f.params.get("detect"):
        items.append("Protrusions by automated detection: compact relief of the height map "
                     "and bright fluorescence of the albedo (paper section 3), measured per "
                     "protrusion (width, height above the surround, crater, colour) and "
                     "counted per colour area; densities per cm\u00b2 by width in "
                     f"{e(sig(p.get('bins_um') or 100, 3) if not isinstance(p.get('bins_um'), list) else 'the given')}"
                     " \u00b5m bins (paper Fig. 4a).")
    t = f.run.get("timings_s") or {}
    if t:
        total = sum(float(v) for v in t.values() if isinstance(v, (int, float)))
        items.append(f"Computed in {sig(total, 2)} s (" + ", ".join(
            f"{e(str(k))} {sig(v, 2)} s" for k, v in t.items()
            if isinstance(v, (int, float))) + ").")
    return ("<section class='appendix' id='methods'><h2>Appendix A: methods and parameters</h2>"
            "<ol>" + "".join(f"<li>{s}</li>" for s in items) + "</ol></section>")


def provenance_html(f: Facts, run_dir: Path, version: str, written: str) -> str:
    """Appendix C (last): version, command, every input with its SHA-256, the files of the run."""
    line = f"<p>Report written {e(written)} by uvps {e(version)}"
    if f.run.get("command"):
        line += (f"; the run made by the <code>{e(str(f.run['command']))}</code> command"
                 + (f" of uvps {e(str(f.run['version']))}" if f.run.get("version") else ""))
    out = ["<section class='appendix' id='provenance'><h2>Appendix C: provenance</h2>",
           line + ".</p>"]
    inputs = f.run.get("inputs") or []
    if inputs:
        rows = [[Raw(f"<code>{e(Path(str(i.get('path', ''))).name)}</code>"),
                 Raw(f"<code class='hash'>{e(str(i.get('sha256') or 'not a file'))}</code>")]
                for i in inputs if isinstance(i, dict)]
        folder = {str(Path(str(i.get("path", ""))).parent) for i in inputs if isinstance(i, dict)}
        where = f" in <code>{e(folder.pop())}</code>" if len(folder) == 1 else ""
        out.append(f"<p>Input files{where} and their SHA-256:</p>")
        out.append(table_html(["File", "SHA-256"], rows, cls="prov"))
    files = [p for p in ("run.json", "lights.json", "protrusions.csv", "regions.csv",
                         "protrusions_manual.csv", "comparison.csv") if (run_dir / p).is_file()]
    if files:
        out.append("<p>Machine-readable: " + ", ".join(
            f"<a href='{e(p)}'>{e(p)}</a>" for p in files) + ".</p>")
    out.append("</section>")
    return "\n".join(out)
