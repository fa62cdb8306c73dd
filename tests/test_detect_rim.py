"""The height cue keeps a small elliptical collapsed crater whole (``height._rim_merges``): its
rim's two ends, higher than its flanks, are one crater's rim, not two protrusions; touching
domes, a ring of three domes and a crater beside a dome stay apart."""
import numpy as np
import pytest
from scipy import ndimage as ndi

from uvps.core.detect import detect_protrusions
from test_detect import add_profile, eq_diameter, scene

PX = 15.0


def elliptical_crater(h, centre, width_um, *, aspect=1.5, angle=0.0, rim_um=35.0, ends=0.2, blur_px=0.6):
    """A small collapsed crater, elliptical: a ring ``sin^2(pi rho)`` (``rho`` the elliptical
    radius, its axes ``width_um sqrt(aspect)`` and ``width_um / sqrt(aspect)``, so ``width_um``
    is its equivalent diameter) whose centre falls to the paint, ``rim_um`` high, the ends of
    its major axis ``ends`` higher than its flanks (``1 + ends cos^2`` of the angle round it:
    what the integration of a narrow rim leaves, its flanks lower), blurred by ``blur_px`` as
    the integrated height is. Returns the crater's own height (added to ``h``)."""
    a = 0.5 * width_um / PX * np.sqrt(aspect)
    b = 0.5 * width_um / PX / np.sqrt(aspect)
    yy, xx = np.mgrid[:h.shape[0], :h.shape[1]].astype(np.float64)
    dx, dy = xx - centre[1], yy - centre[0]
    u = (np.cos(angle) * dx + np.sin(angle) * dy) / a
    v = (-np.sin(angle) * dx + np.cos(angle) * dy) / b
    rho = np.hypot(u, v)
    z = np.where(rho < 1, np.sin(np.pi * rho) ** 2 * np.where(rho < 0.5, 0.5 + rho, 1.0), 0.0)
    z *= rim_um * (1 + ends * u ** 2 / np.maximum(rho ** 2, 1e-12))
    z = ndi.gaussian_filter(z, blur_px).astype(np.float32)
    h += z
    return z


def dome(h, centre, width_um, height_um=None):
    """A dome ``width_um`` wide and a quarter as high, the higher surface winning where it
    touches another (as protrusions that grew into each other)."""
    own = np.zeros_like(h)
    add_profile(own, centre, width_um, PX, 0.25 * width_um if height_um is None else height_um, "dome")
    return own


@pytest.mark.parametrize("width_um, angle, seed", [(110.0, 0.0, 0), (120.0, 0.5, 1), (130.0, 1.2, 2),
                                                   (140.0, 2.0, 3), (150.0, 2.6, 4), (120.0, 0.9, 5)])
def test_small_elliptical_collapsed_crater_is_one_protrusion(width_um, angle, seed):
    """A crater 110-150 um wide, aspect 1.5, rim ~35 um over a pit ~10 um, its ends ~20 % above
    its flanks: ``split_fraction`` finds a peak at each end and the watershed cut through the
    pit (two protrusions of half its width). The two ends together enclose the pit, which
    neither does alone: one crater, its width within 20 %. Beside it, on the same noisy paint,
    a dome 90 um wide 2 px from its foot stays its own, and two touching domes stay two."""
    alb, h = scene((90, 120), seed=seed)
    crater = elliptical_crater(h, (45.3, 40.6), width_um, angle=angle)
    pit = crater[44:47, 39:42].min()
    ring = crater.max()
    assert 30 <= ring <= 45 and pit <= 0.45 * ring                 # a collapsed crater's rim and pit
    r_out = 0.5 * width_um / PX * np.sqrt(1.5)                       # its half major axis (px)
    neighbour = (45, int(round(40.6 - r_out - 2 - 3)))               # a 90 um dome 2 px from its foot
    h += dome(h, neighbour, 90.0)
    pair = np.maximum(dome(h, (30, 90), 150.0), dome(h, (30 + 7.5, 90 + 4.5), 120.0))
    h += pair                                                        # centres 0.7 x the radii apart
    det = detect_protrusions(alb, h, pixel_size_um=PX)
    lab = det.labels
    on_rim = np.unique(lab[crater > 0.5 * ring])
    assert on_rim.tolist() == [int(lab[45, 41])] and on_rim[0] > 0, on_rim
    assert abs(eq_diameter(lab == on_rim[0]) * PX / width_um - 1) <= 0.20
    assert lab[neighbour] > 0 and lab[neighbour] != on_rim[0]
    assert lab[30, 90] > 0 and lab[37, 94] > 0 and lab[30, 90] != lab[37, 94]
    assert lab.max() == 4


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ring_of_three_domes_and_a_crater_beside_a_dome_stay_apart(seed):
    """What the rim rule must not join: three domes 120 um wide touching in a ring round a
    hollow (any two of them enclose it only with the third), two domes side by side 1 px
    apart, and a caldera 300 um wide (its pit its own) touching a 120 um dome nearly as high."""
    alb, h = scene((110, 150), seed=seed)
    r = 120.0 / PX / 2
    ring = [(30 + 1.4 * r * np.sin(t), 35 + 1.4 * r * np.cos(t)) for t in (0.3, 0.3 + 2.1, 0.3 + 4.2)]
    h += np.maximum.reduce([dome(h, c, 120.0) for c in ring])
    h += dome(h, (85, 20), 120.0) + dome(h, (85, 20 + 2 * r + 1), 120.0)
    cal = np.zeros_like(h)
    add_profile(cal, (60, 110), 300.0, PX, 70.0, "crater")
    h += np.maximum(cal, dome(h, (60, 110 + 10 + 3.5), 120.0, 0.9 * cal.max()))   # of a height
    det = detect_protrusions(alb, h, pixel_size_um=PX)
    lab = det.labels
    at = [tuple(int(round(x)) for x in c) for c in ring] + [(85, 20), (85, int(round(20 + 2 * r + 1)))]
    ids = [lab[c] for c in at]
    assert all(ids) and len(set(ids)) == 5, ids
    assert lab[60, 110 + 6] > 0 and lab[60, 124] > 0 and lab[60, 110 + 6] != lab[60, 124]
    assert lab.max() == 7
