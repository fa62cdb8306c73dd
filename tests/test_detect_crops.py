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
