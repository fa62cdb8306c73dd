"""Rules: the rejection table, each rule declared once (module docstring of
:mod:`uvps.core.detect`, step 7).

A :class:`Rule` holds the rule's name, the words that explain a rejection to a conservator, the
quantity it tests and the test in prose, the :class:`~.params.DetectionParams` fields it owns
with their ranges, the :class:`~.features.CandidateFeatures` it reads, and the test itself. From
the table :data:`RULES` come :data:`REJECTION_RULES` (the public rows), the validation of the
options (:data:`PARAM_RANGES`), the CLI's help (``uvps.commands.protrusions``), the docs' tables
(:func:`rules_markdown`, ``scripts/detection_docs.py``), the Fiji wording
(``jython_lib/uvps_fiji/rejection_words.py``), and the along-stroke rescue's checks
(:mod:`.along_stroke` calls the rules marked ``rescue`` on a bump's own measurements).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, NamedTuple

import numpy as np

from ._common import Thresholds
from .features import CandidateFeatures
from .params import CUE_RANGES, INF, DetectionParams, Range

#: A candidate whose normals tilt less than this on average (deg) is flat (``flat_bright``,
#: ``weave``): bare primer and the paint between protrusions lie within a degree of the canvas
#: plane, while a protrusion 0.1-0.4 as high as it is wide tilts its flanks by 10-40 deg.
FLAT_TILT_DEG = 1.0


class RejectionRule(NamedTuple):
    """One row of the rejection table: the rule's name, the quantity it tests, the test."""

    name: str
    quantity: str
    test: str


class RuleContext(NamedTuple):
    """What a rule's test reads beside the features: the thresholds, the pixel size, the
    options, the strokes' own statistics (:func:`.strokes._stroke_slope`, :func:`.strokes._ripples`),
    and whether the candidate is a bump measured by the along-stroke rescue (``bump``: its own
    footprint's measurements, see :data:`RULES`)."""

    th: Thresholds
    px: float
    p: DetectionParams
    on_long: object = False
    stroke_min: float = 0.0
    ripple: object = False
    bump: bool = False


@dataclass(frozen=True)
class Rule:
    """One rejection rule, declared once."""

    name: str
    words: str                  # what the rejected thing was, in a conservator's words (Fiji's Log, the report)
    quantity: str               # what it measures (docs, REJECTION_RULES)
    test: str                   # its test (docs, REJECTION_RULES)
    params: dict                # the DetectionParams fields it owns -> Range
    reads: tuple                # the CandidateFeatures fields it reads
    fails: Callable             # (features, RuleContext) -> bool per candidate
    rescue: bool = False        # re-applied by the along-stroke rescue to a bump


def _slope(f, c: RuleContext):
    """Flank slope relief / (width / 2)."""
    return f.relief / np.maximum(f.eqd * c.px / 2, 1e-12)


def _too_small(f, c: RuleContext):
    return f.eqd < c.th.min_w


def _too_large(f, c: RuleContext):
    return f.eqd > c.th.max_w


def _ridge(f, c: RuleContext):
    """For a bump (``c.bump``) the axes are compared as ``minor < ridge_axis_ratio x major`` (its
    outline's second moments) and the compact-fraction clause is not tested (its excess is
    compact by construction), as the rescue always did."""
    p = c.p
    long_axes = f.major * c.px >= p.ridge_min_length_um
    if c.bump:
        return (f.elongation > p.ridge_elongation) | ((f.minor < p.ridge_axis_ratio * f.major) & long_axes)
    compact = np.where(f.relief_disc > 0, f.relief / np.maximum(f.relief_disc, 1e-12), 1.0)
    return ((f.elongation > p.ridge_elongation) | ((f.axis_ratio < p.ridge_axis_ratio) & long_axes)
            | (~f.has_h & (f.relief_disc >= c.th.relief_um) & (compact < p.ridge_compact_fraction)))


def _stroke(f, c: RuleContext):
    return c.on_long & ((_slope(f, c) < c.stroke_min) | c.ripple)


def _crack(f, c: RuleContext):
    return (f.hole_fraction > c.p.max_hole_fraction) | (f.crack_fraction > c.p.max_crack_fraction)


def _flat(f, c: RuleContext):
    return (f.relief < c.th.relief_um) | (f.tilt_deg < FLAT_TILT_DEG)


def _flat_bright(f, c: RuleContext):
    return _flat(f, c) & f.has_a & ~f.has_h


def _artefact(f, c: RuleContext):
    """For a bump the unmeasured share is compared as counts, ``unmeasured pixels >
    max_unmeasured_fraction x outline pixels``, as the rescue always did."""
    p = c.p
    if c.bump:
        return (f.mismatch > p.max_mismatch) | (f.unmeasured_px > p.max_unmeasured_fraction * f.area_px)
    return (f.mismatch > p.max_mismatch) | (f.unmeasured > p.max_unmeasured_fraction)


def _weave(f, c: RuleContext):
    """For a bump: relief under the threshold or slope under ``slope_min`` (no tilt, no glow:
    a bump on a stroke meets the weave's slope whatever its glow), as the rescue always did."""
    slope = _slope(f, c)
    if c.bump:
        return (f.relief < c.th.relief_um) | (slope < c.th.slope_min)
    # the weave does not glow: a candidate whose glow is its own meets the paint's floor, its
    # relief the larger of the local one and the one over the disc opening (on a stroke's
    # curved flank the plane through its ring, or the compact relief, leaves it only its top)
    own = f.has_a & (f.own_glow >= c.p.own_glow_fraction)
    half = np.maximum(f.eqd * c.px / 2, 1e-12)
    weave = np.where(own, np.maximum(f.relief, f.relief_disc) / half < 2 * c.p.min_relief_ratio,
                     slope < c.th.slope_min)
    return _flat(f, c) | weave


#: The rejection table, applied in this order (a candidate keeps the first rule it fails).
RULES = (
    Rule("too_small", "narrower than the smallest width counted",
         "equivalent diameter 2 sqrt(area / pi)", "< min_width_um",
         {"min_width_um": Range(0.0, "max_width_um", True, True)}, ("eqd",), _too_small, rescue=True),
    Rule("ridge", "elongated: brush strokes or crack lips",
         "elongation area / (pi r_in^2) (r_in: largest inscribed radius, its holes filled); "
         "minor / major axis; compact fraction (relief within L / relief over the "
         "surround, for raised areas without a compact peak)",
         "elongation > ridge_elongation, or axis ratio < ridge_axis_ratio with a major "
         "axis >= ridge_min_length_um, or compact fraction < ridge_compact_fraction",
         {"ridge_elongation": Range(0.0, INF, lo_open=True), "ridge_axis_ratio": Range(0.0, 1.0),
          "ridge_min_length_um": Range(0.0, INF), "ridge_compact_fraction": Range(0.0, 1.0)},
         ("elongation", "axis_ratio", "major", "has_h", "relief", "relief_disc"), _ridge, rescue=True),
    Rule("stroke", "ripples, piled ends and crossings of brush strokes",
         "on a long structure (the disc top-hat exceeds the compact relief under "
         "it by the relief threshold and a quarter of its relief), without the albedo's "
         "glow: flank slope relief / (width / 2)",
         "< stroke_slope_k x the median flank slope of the bumps on long structures "
         "(measured per image, at least 8 of them): a ripple, a piled end or a crossing "
         "of a brush stroke; or a member of an evenly spaced row of similar such bumps "
         "(_ripples: a stroke's ripples) (ridge, stroke and crack: unless its excess "
         "over the stroke's profile continued along the stroke is a closed, steep bump "
         "whose mismatch is within max_mismatch, _bumps_on_strokes; never for a ripple)",
         {"stroke_slope_k": Range(0.0, INF, hi_open=True, note="0 disables"),
          "ripple_reach": Range(0.0, INF, hi_open=True, note="0 disables")},
         ("relief", "eqd", "has_h", "has_a", "under", "centroid"), _stroke, rescue=True),
    Rule("crack", "pieces cut off by cracks, or rims of cupped paint",
         "crack fraction: of the 2-px ring around it, the part in a crack (black "
         "top-hat over crack_width_um) at least half as deep as it is high, counted where "
         "the groove runs on 2 crack widths beyond it (a pocket between touching "
         "protrusions ends with them); hole fraction: "
         "area enclosed by the footprint but below its level / filled area",
         "crack fraction > max_crack_fraction (a piece of a cupped island's rim or of a "
         "stroke cut off by a crack), or hole fraction > max_hole_fraction (a crater's "
         "floor stands above the paint, a cupped island's rim encloses its dish)",
         {"max_crack_fraction": Range(0.0, 1.0), "max_hole_fraction": Range(0.0, 1.0),
          "crack_width_um": Range(0.0, INF, True, True)},
         ("crack_fraction", "hole_fraction"), _crack, rescue=True),
    Rule("too_large", "wider than the largest width counted", "equivalent diameter", "> max_width_um",
         {"max_width_um": Range("min_width_um", INF, True, True)}, ("eqd",), _too_large, rescue=True),
    Rule("flat_bright", "bright but flat (bare primer)",
         "relief (um) of a candidate found by the albedo only; mean tilt",
         "relief < relief threshold or tilt < 1 deg: bare primer",
         {}, ("relief", "tilt_deg", "has_a", "has_h"), _flat_bright),
    Rule("artefact", "relief the normals do not hold (integration artefacts)",
         "mismatch: over the footprint, mean |e - mean e| / mean |g - mean g|, "
         "g the normals' slope, e the height's slope minus g (with normals only); "
         "unmeasured fraction: the part of the footprint within 2 px of a pixel with no "
         "measurement (non-finite albedo, normals or height)",
         "mismatch > max_mismatch: relief the normals do not hold is an integration "
         "artefact (e.g. along a crack whose walls the lamps do not light; the pixels "
         "left out of the height's integration, left_out, set aside when the rest is at "
         "least half the footprint); or unmeasured "
         "fraction > max_unmeasured_fraction: relief made by the integration's fill of a hole",
         {"max_mismatch": Range(0.0, INF, note="inf disables"), "max_unmeasured_fraction": Range(0.0, 1.0)},
         ("mismatch", "unmeasured"), _artefact, rescue=True),
    Rule("weave", "canvas weave or paint texture, too flat for a protrusion",
         "relief (um); flank slope relief / (width / 2); mean tilt; own glow: "
         "of the albedo components it overlaps, the part inside it",
         "relief < relief threshold, or slope < max(2 min_relief_ratio, weave_slope_k x "
         "the weave's RMS slope) unless it glows and its own glow is at least "
         "own_glow_fraction (the weave does not glow; a piece of a glowing stroke holds "
         "a small part of the glowing paint it is cut from): then max(relief, relief over "
         "the disc opening) / (width / 2) < 2 min_relief_ratio; or tilt < 1 deg",
         {"weave_slope_k": Range(0.0, INF, hi_open=True), "min_relief_ratio": Range(0.0, INF, hi_open=True),
          "own_glow_fraction": Range(0.0, INF, lo_open=True, note="above 1 disables")},
         ("relief", "relief_disc", "eqd", "tilt_deg", "has_a", "own_glow"), _weave, rescue=True),
)
REJECTION_RULES = tuple(RejectionRule(r.name, r.quantity, r.test) for r in RULES)
REJECTION_REASONS = tuple(r.name for r in RULES)
#: Every option's range: the rules' own and the cues' (:data:`.params.CUE_RANGES`).
PARAM_RANGES = {**{k: v for r in RULES for k, v in r.params.items()}, **CUE_RANGES}
#: The rejection words in a conservator's words (Fiji's Log: ``rejection_words.py``).
REJECTION_WORDS = {r.name: r.words for r in RULES}


def _apply_rules(f: CandidateFeatures, th: Thresholds, px: float, p: DetectionParams,
                 on_long: np.ndarray, stroke_min: float, ripple: np.ndarray) -> np.ndarray:
    """The rule of :data:`RULES` each candidate fails first ("" = kept); ``on_long``,
    ``stroke_min``: :func:`.strokes._stroke_slope`; ``ripple``: :func:`.strokes._ripples`."""
    ctx = RuleContext(th, px, p, on_long, stroke_min, ripple)
    reason = np.full(f.lbl.size, "", dtype="<U13")
    for rule in RULES:
        reason[rule.fails(f, ctx) & (reason == "")] = rule.name
    return reason


def _rescue_fails(bump, ctx: RuleContext) -> bool:
    """Whether a bump of the along-stroke rescue (its own measurements: ``eqd``,
    ``elongation``, ``major``, ``minor``, ``relief``, ``crack_fraction``, ``hole_fraction``,
    ``mismatch``, ``unmeasured_px``, ``area_px``) fails one of the rules marked ``rescue``."""
    ctx = ctx._replace(bump=True)
    return any(bool(r.fails(bump, ctx)) for r in RULES if r.rescue)


def rules_markdown() -> str:
    """The rejection table as Markdown, from :data:`RULES` (``docs/architecture.md`` and
    ``docs/protrusions.md`` hold it between ``<!-- rules:begin -->`` and ``<!-- rules:end -->``;
    ``scripts/detection_docs.py`` writes it, ``tests/test_detect_package.py`` checks it)."""
    d = DetectionParams()
    rows = ["| rule | in a conservator's words | quantity | rejected when | options (default, range) |",
            "|---|---|---|---|---|"]
    for r in RULES:
        opts = ", ".join(f"`{k}` ({getattr(d, k):g}, {v.text()})" for k, v in r.params.items()) or "-"
        cells = (f"`{r.name}`{' *' if r.rescue else ''}", r.words, r.quantity, r.test, opts)
        rows.append("| " + " | ".join(c.replace("|", "\\|") for c in cells) + " |")
    return ("\n".join(rows) + "\n\nApplied in this order; a candidate keeps the first rule it fails. "
            "* the along-stroke rescue re-applies the rule to a bump's own measurements "
            "(`rules._rescue_fails`: the `ridge` rule compares its axes as `minor < "
            "ridge_axis_ratio x major` without the compact-fraction clause, `artefact` its "
            "unmeasured pixels as counts, `weave` its relief and slope without the tilt and the "
            "glow exemption). Generated from `uvps.core.detect.rules.RULES` by "
            "`scripts/detection_docs.py`.\n")


def jython_words_module() -> str:
    """``jython_lib/uvps_fiji/rejection_words.py``: :data:`REJECTION_WORDS` for the Fiji side
    (Jython 2.7 cannot import this package), written by ``scripts/detection_docs.py``."""
    body = "".join(f"    {r.name!r}: {r.words!r},\n" for r in RULES)
    return ('"""The detection\'s rejection rules in a conservator\'s words, for the Fiji Log.\n\n'
            "Generated from ``uvps.core.detect.rules.RULES`` by ``scripts/detection_docs.py``: do not edit\n"
            '(``tests/test_detect_package.py`` fails when it is stale)."""\n\n'
            "REJECTION_WORDS = {\n" + body + "}\n")
