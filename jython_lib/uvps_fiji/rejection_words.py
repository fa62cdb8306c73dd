"""The detection's rejection rules in a conservator's words, for the Fiji Log.

Generated from ``uvps.core.detect.rules.RULES`` by ``scripts/detection_docs.py``: do not edit
(``tests/test_detect_package.py`` fails when it is stale)."""

REJECTION_WORDS = {
    'too_small': 'narrower than the smallest width counted',
    'ridge': 'elongated: brush strokes or crack lips',
    'stroke': 'ripples, piled ends and crossings of brush strokes',
    'crack': 'pieces cut off by cracks, or rims of cupped paint',
    'too_large': 'wider than the largest width counted',
    'flat_bright': 'bright but flat (bare primer)',
    'artefact': 'relief the normals do not hold (integration artefacts)',
    'weave': 'canvas weave or paint texture, too flat for a protrusion',
}
