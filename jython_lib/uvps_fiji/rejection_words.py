"""The detection's rejection rules in a conservator's words, for the Fiji Log.

Generated from ``uvps.core.detect.rules.RULES`` by ``scripts/detection_docs.py``: do not edit
(``tests/test_detect_package.py`` fails when it is stale)."""

REJECTION_WORDS = {
    'too_small': 'narrower than the smallest width',
    'ridge': 'ridges and brush strokes',
    'stroke': 'ripples, piled ends and crossings of brush strokes',
    'crack': 'crack edges and cupped rims',
    'too_large': 'wider than the largest width',
    'flat_bright': 'bright but flat (bare primer)',
    'artefact': 'height artefacts the normals do not show',
    'weave': 'canvas weave',
}
