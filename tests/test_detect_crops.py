"""The detector's steps computed on crops give the whole image's results to the bit: the peaks'
watershed on the mask's components packed side by side (``height._basins``)."""
import numpy as np
from scipy import ndimage as ndi
from skimage.segmentation import watershed

from uvps.core.detect.height import _basins


def _bumps(seed: int, shape=(300, 400), n=60) -> tuple:
    """Blurred random bumps (a relief ``t`` >= 0) and one marker pixel at each local maximum
    above 1 (numbered in raster order)."""
    rng = np.random.default_rng(seed)
    t = np.zeros(shape, np.float32)
    t[rng.integers(0, shape[0], n), rng.integers(0, shape[1], n)] = rng.uniform(50, 400, n)
    t = ndi.gaussian_filter(t, 3.0).astype(np.float32)
    peak = (t == ndi.maximum_filter(t, 3)) & (t > 1.0)
    markers, _ = ndi.label(peak)
    return t, markers.astype(np.int32)


def test_basins_are_the_whole_images_watershed():
    for seed in range(4):
        t, markers = _bumps(seed)
        assert markers.max() > 10
        ref = watershed(-t, markers, mask=(t >= 0.5) | (markers > 0))
        assert np.array_equal(_basins(t, markers, 0.5), ref)


def test_basins_with_tied_markers_flood_the_whole_image():
    t, markers = _bumps(7)
    t = np.round(t)                   # plateaus: markers tied in value, the whole image flooded
    peak = (t == ndi.maximum_filter(t, 3)) & (t > 1.0)
    markers = ndi.label(peak)[0].astype(np.int32)
    ref = watershed(-t, markers, mask=(t >= 0.5) | (markers > 0))
    assert np.array_equal(_basins(t, markers, 0.5), ref)


def test_basins_without_markers_are_empty():
    t, _ = _bumps(1)
    assert not _basins(t, np.zeros(t.shape, np.int32), 0.5).any()


def test_touching_pairs_are_the_shifted_images():
    from uvps.core.detect._common import STEPS_4, STEPS_8, _touching
    rng = np.random.default_rng(3)
    lab = ndi.label(rng.random((60, 70)) > 0.45)[0]
    lab[rng.random(lab.shape) > 0.8] += 1                   # touching labels
    lab = lab.astype(np.int32)
    shifts = {(0, 1): (lab[:, :-1], lab[:, 1:]), (1, 0): (lab[:-1], lab[1:]),
              (1, 1): (lab[:-1, :-1], lab[1:, 1:]), (1, -1): (lab[:-1, 1:], lab[1:, :-1])}
    for steps in (STEPS_4, STEPS_8):
        i, j = _touching(lab, steps)
        got = sorted(zip(lab.ravel()[i], lab.ravel()[j]))
        ref = []
        for s in steps:
            a, b = shifts[s]
            sel = (a > 0) & (b > 0) & (a != b)
            ref += list(zip(a[sel], b[sel]))
        assert got == sorted(ref) and len(got) > 50


def test_packed_h_maxima_are_each_images_own():
    from skimage.morphology import h_maxima
    from uvps.core.detect._common import _packed_h_maxima
    t, _ = _bumps(5, shape=(200, 260), n=40)
    low = t >= 2.0
    comp, n = ndi.label(low, structure=np.ones((3, 3)))
    images, owns = [], []
    for k, sl in enumerate(ndi.find_objects(comp)):
        own = comp[sl] == k + 1
        owns.append(own)
        images.append(np.where(own, np.log(t[sl].astype(np.float64) + 1.0), -1.0))
    images.append(np.full((1, 1), 3.0))            # no background pixel: its own call
    owns.append(np.ones((1, 1), bool))
    got = _packed_h_maxima(images, owns, -1.0, (0.3, 0.1))
    assert got[-1] is None and sum(g is not None for g in got) >= 0.8 * n > 20
    for im, own, g in zip(images, owns, got):
        if g is not None:
            for dyn, m in zip((0.3, 0.1), g):
                assert np.array_equal(m.astype(bool) & own, h_maxima(im, dyn).astype(bool) & own)


def test_kept_components_are_a_second_labelling():
    from uvps.core.detect._common import _kept_components
    rng = np.random.default_rng(11)
    for structure in (None, np.ones((3, 3))):
        comp, n = ndi.label(rng.random((80, 90)) > 0.6, structure=structure)
        keep = rng.random(n + 1) > 0.4
        ref, k_ref = ndi.label(keep[comp] & (comp > 0), structure=structure)
        at, new, k = _kept_components(comp, keep)
        got = np.zeros(comp.shape, np.int32)
        got.ravel()[at] = new
        assert k == k_ref > 10 and np.array_equal(got, ref)
