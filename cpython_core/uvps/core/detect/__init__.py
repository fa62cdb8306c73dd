"""Automated metal-soap protrusion detection from the height map and the fluorescence albedo.

The paper (Salvant et al., "Automated Protrusion Detection") builds mask 1 from a colour threshold
plus template matching on the albedo and mask 2 from OpenCV blob detection on the height map, and
takes their union; it under-counts and is fooled by brush-stroke ridges and bare primer. Here every
threshold is a physical quantity measured on the data (the height noise, the weave's spectrum) or
a stated property of a protrusion, and each cue is one function (``docs/architecture.md``,
"Detection cues", says what each assumes):

1. **Surface** (:func:`_surface`). The height noise is a robust MAD of the high-passed height
   (second differences). The canvas weave, a few sharp peaks of the height's power spectrum, is
   measured (periods, RMS amplitude, RMS slope) and subtracted (:func:`_remove_weave`).
2. **Compact relief** (:func:`_compact_relief`). ``t = h - min(h, A(h))``, ``A`` the *diameter
   opening*: every level set of ``h`` whose extent reaches ``L = 1.3 x max_width_um`` stays in
   ``A``, so ``t`` holds only what is enclosed within less than ``L``: protrusions (domes, craters,
   mesas, any outline) stand out; the canvas bow, brush strokes, cupped islands and crack lips
   (all longer than ``L``) vanish. ``A`` is computed on f x f block maxima (``f = L / 16`` px, 5 at
   15 um per pixel); a small object in the block next to a stroke's is then taken into the
   stroke's level sets, so around such objects the exact level sets decide (:func:`_beside_long`).
3. **Height cue** (:func:`_height_cue`, :func:`_local_footprints`). Peaks of ``t`` at least the
   relief threshold ``max(min_dynamic_um, dynamic_k x smoothed noise)`` high, two peaks being two
   protrusions when the saddle between them lies ``split_fraction`` below the lower one, or
   ``weak_split_fraction`` below it when the lower one is at most three quarters as high and
   the two do not lie along a ridge (:func:`_weak_splits`); a smaller dome on a taller one's
   flank with no peak of its own is marked by the blob its curvature makes there
   (:func:`_shoulder_markers`). A watershed of ``-t`` from the markers splits touching
   clusters. Each footprint is then re-drawn over a robust plane through its
   surround (a protrusion on a slope keeps its whole relief), where the relief exceeds
   ``footprint_fraction`` of its peak.
4. **Albedo cue** (:func:`_albedo_cue`). Brightness contrast ``L / L_bg - 1`` above
   ``albedo_contrast`` whose component matches a disc template (:func:`cv2.matchTemplate`). It
   only adds: a protrusion that does not fluoresce is found by its relief alone.
5. **Long raised areas** (:func:`_long_areas`). What a disc top-hat raises but ``t`` does not
   (strokes, crack lips) become candidates, so that the ``ridge`` rule counts them.
6. **The strokes' own statistics** (:func:`_stroke_slope`). Compact peaks with a long structure
   under them (a stroke's ripples, piled ends and crossings, or a protrusion on a stroke) and
   no albedo glow; their median flank slope, measured per image, sets the least slope of a
   protrusion among them (``stroke_slope_k`` times it; the ``stroke`` rule). Among them, the
   members of an evenly spaced row of similar bumps are a stroke's ripples (:func:`_ripples`),
   rejected by the same rule whatever their slope.
7. **Union** (:func:`_union`) and **rejection** (:func:`_candidate_features`,
   :func:`_apply_rules`) by the table :data:`REJECTION_RULES`, first match wins; each rejected
   candidate keeps its rule (``Detection.diagnostics["candidate_reasons"]``), the counts are
   ``Detection.rejected``.
8. **Bumps on strokes** (:func:`_bumps_on_strokes`). A compact peak on a long structure that the
   ``ridge``, ``crack`` or ``stroke`` rule rejects, or a glowing candidate without a compact
   peak on one (a small protrusion on a taller stroke's flank), is measured again over the
   stroke's own profile continued along the stroke (the height, cracks filled where they cut
   it, minus its opening by a line laid in the direction the height around it runs on): a
   closed, compact bump as steep as the strokes' own statistics ask, whose height the normals
   hold (the ``artefact`` rule's mismatch), is a protrusion on the stroke and is kept, outlined
   by that excess.

Every length option is in micrometres and converted with ``pixel_size_um``.

The stages are one module each: :mod:`.surface` (with :mod:`.weave`), :mod:`.height` (with
:mod:`.footprints`), :mod:`.albedo`, :mod:`.candidates`, :mod:`.features`, :mod:`.strokes`, :mod:`.rules`,
:mod:`.along_stroke`, composed by :mod:`.detector`; the options and the result are in
:mod:`.params`, the compiled kernels with their numpy twins in :mod:`._kernels`
(``docs/architecture.md``, "Detection cues").
"""
from __future__ import annotations

from .detector import detect_protrusions
from .params import Detection, DetectionParams
from .rules import REJECTION_REASONS, REJECTION_RULES, REJECTION_WORDS, RejectionRule

# the stages' own names that the tests and benchmarks read as ``uvps.core.detect.<name>``
from ._common import Thresholds, _edt, _expand_labels, _holes, _median  # noqa: F401,E402
from ._kernels import (_flood_beside, _robust_plane, _robust_plane_kernel,  # noqa: F401,E402
                       _robust_plane_numpy)
from .albedo import _brightness  # noqa: F401,E402
from .features import (CandidateFeatures, _axis_lengths, _crack_fraction,  # noqa: F401,E402
                       _hole_area, _inscribed_radius)
from .height import (WEAK_HOST_RATIO, _height_cue, _isotropy_at, _log_curvature,  # noqa: F401,E402
                     _peak_markers, _shoulder_markers, _weak_splits)
from .rules import _apply_rules  # noqa: F401,E402
from .strokes import _ripples  # noqa: F401,E402
from .surface import _beside_long, _diameter_opening, _surface, _thresholds  # noqa: F401,E402
from .weave import _fit_sinusoids, _sinusoids  # noqa: F401,E402

__all__ = ["DetectionParams", "Detection", "detect_protrusions", "REJECTION_REASONS",
           "REJECTION_RULES", "REJECTION_WORDS", "RejectionRule"]
