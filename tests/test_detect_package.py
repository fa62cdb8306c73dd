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
from uvps.core.detect.params import PARAM_RANGES
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
