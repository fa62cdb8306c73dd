"""The detector as a package of stages (``uvps.core.detect``): small modules, short functions,
every option range-checked, every name the rest of the project imports still importable."""
import ast
import math
from dataclasses import fields, replace
from pathlib import Path

import numpy as np
import pytest

import uvps.core.detect as detect
from uvps.core.detect import DetectionParams, detect_protrusions
from uvps.core.detect.params import CUE_RANGES
from uvps.core.detect.rules import PARAM_RANGES, RULES
from uvps.errors import UVPSInputError

PACKAGE = Path(detect.__file__).parent
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 60


def _body_lines(fn: ast.FunctionDef) -> int:
    """Lines of a function without its docstring."""
    body = fn.body
    if isinstance(body[0], ast.Expr) and isinstance(getattr(body[0], "value", None), ast.Constant) \
            and isinstance(body[0].value.value, str):
        if len(body) == 1:
            return 0
        body = body[1:]
    return fn.end_lineno - body[0].lineno + 1


def test_modules_and_functions_are_small():
    long = []
    for path in sorted(PACKAGE.glob("*.py")):
        src = path.read_text()
        assert len(src.splitlines()) <= MAX_MODULE_LINES, path.name
        long += [f"{path.name}:{n.name} {_body_lines(n)}" for n in ast.walk(ast.parse(src))
                 if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))
                 and _body_lines(n) > MAX_FUNCTION_LINES]
    assert long == []
    assert _body_lines(ast.parse("def f():\n    '''doc\n    more'''\n    a = 1\n    return a\n").body[0]) == 2


def test_the_public_and_tested_names_are_exposed():
    for name in detect.__all__ + ["Thresholds", "CandidateFeatures", "WEAK_HOST_RATIO", "_ripples",
                                  "_apply_rules", "_robust_plane_kernel", "_flood_beside", "_surface"]:
        assert hasattr(detect, name), name


def test_every_option_has_a_range_and_is_checked():
    assert set(PARAM_RANGES) == {f.name for f in fields(DetectionParams)}
    alb, h = np.ones((32, 32)), np.zeros((32, 32))
    for name, r in PARAM_RANGES.items():
        lo = getattr(DetectionParams(), r.lo) if isinstance(r.lo, str) else r.lo
        hi = getattr(DetectionParams(), r.hi) if isinstance(r.hi, str) else r.hi
        bad = [float("nan")]
        if isinstance(r.lo, str) or math.isfinite(lo):
            bad.append(lo if r.lo_open else lo - 1)
        if isinstance(r.hi, str) or math.isfinite(hi):
            bad.append(hi if r.hi_open else hi + 1)
        for v in bad:
            with pytest.raises(UVPSInputError, match=name):
                detect_protrusions(alb, h, pixel_size_um=15.0, params=replace(DetectionParams(), **{name: v}))
    detect_protrusions(alb, h, pixel_size_um=15.0, params=DetectionParams(
        max_mismatch=np.inf, stroke_slope_k=0, along_stroke_k=0, shoulder_width_um=0, ripple_reach=0,
        weave_factor=0, beside_long_fraction=0, weak_split_fraction=0, own_glow_fraction=2.0))


def test_each_option_range_is_declared_once():
    """A rule owns its options' ranges; the cues' are in CUE_RANGES; none in both."""
    owned = [k for r in RULES for k in r.params]
    assert len(owned) == len(set(owned)) and not set(owned) & set(CUE_RANGES)
    feats = {f.name for f in fields(detect.CandidateFeatures)}
    for r in RULES:
        assert set(r.reads) <= feats, r.name
        assert r.words and r.quantity and r.test


def test_texts_generated_from_the_rules_are_current():
    """docs/architecture.md's and docs/protrusions.md's rule tables and the Fiji side's words
    are written from the declarations (``python scripts/detection_docs.py``)."""
    import sys
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "scripts"))
    import detection_docs
    stale = [str(p) for p, t in detection_docs.expected().items() if p.read_text(encoding="utf-8") != t]
    assert stale == [], "stale: run python scripts/detection_docs.py"
    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "jython_lib"))
    from uvps_fiji import bridge_logic
    assert bridge_logic.REJECTION_WORDS == {r.name: r.words for r in RULES}
    assert set(bridge_logic.REJECTION_WORDS) == set(detect.REJECTION_REASONS)


def test_each_rule_reads_the_features_it_declares():
    """Run on a few made-up candidates, each rule's test reads only the features it declares."""
    from uvps.core.detect import Thresholds
    from uvps.core.detect.rules import RuleContext

    n = 4
    rng = np.random.default_rng(0)
    vals = {f.name: rng.uniform(0.1, 3.0, n) for f in fields(detect.CandidateFeatures)}
    vals.update(lbl=np.arange(1, n + 1), has_h=np.array([True, False, True, False]),
                has_a=np.array([True, True, False, False]), centroid=rng.uniform(0, 50, (n, 2)))
    feats = detect.CandidateFeatures(**vals)

    class Reads:
        def __init__(self):
            self.seen = set()

        def __getattr__(self, name):
            self.seen.add(name)
            return getattr(feats, name)

    ctx = RuleContext(Thresholds(1.0, 0.1, 2.0, 60.0), 15.0, DetectionParams(),
                      np.ones(n, bool), 0.2, np.zeros(n, bool))
    for r in RULES:
        spy = Reads()
        out = r.fails(spy, ctx)
        assert out.shape == (n,) and out.dtype == bool, r.name
        assert spy.seen <= set(r.reads), (r.name, spy.seen - set(r.reads))
