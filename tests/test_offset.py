"""The additive term of a capture (black level, stray light): measured from the images, given, removed."""
import json

import numpy as np
import pytest

from uvps.errors import UVPSInputError
from uvps.core.stack import Capture
from uvps.core.offset import AdditiveTerm, OffsetImages, estimate_additive, known_additive
from uvps.core.pipeline import RunOptions, remove_additive
from uvps.testing.synthetic import make_capture


@pytest.fixture(scope="module")
def small():
    """A 600 x 800 RGB capture (9 x 12 mm), 8 lamps, no offset, and the same with a black level per
    channel. (The cue needs several colour areas: on 300 x 400 px the error is ~3x larger.)"""
    clean = make_capture(shape=(600, 800), n_lights=8, seed=5)
    black = make_capture(shape=(600, 800), n_lights=8, seed=5, black_level=(300.0, 200.0, 120.0))
    return clean, black


def _capture(images):
    K = images.shape[0]
    return Capture(images=images, files=[f"u{k}.tif" for k in range(K)], pixel_size_um=15.0, mask=None,
                   saturation=65535.0, light_directions=None, light_positions_mm=None, bit_depth="uint16")


def test_black_level_is_measured_per_channel_within_its_standard_error(small):
    _, black = small
    term = estimate_additive(black.images, saturation=65535)
    truth = np.array([300.0, 200.0, 120.0])
    err = term.mean - truth
    # within 4 standard errors per channel, and the grey level (what the lights see) within 0.1 % of
    # the median signal
    assert np.all(np.abs(err) <= 4 * term.stderr + 1.0), (term.mean, term.stderr)
    assert abs(err.mean()) < 0.001 * term.median_signal, (term.mean, term.median_signal)
    assert term.source == "estimated" and term.stderr.shape == (3,)


def test_no_black_level_measures_zero(small):
    clean, _ = small
    term = estimate_additive(clean.images, saturation=65535)
    assert np.all(np.abs(term.mean) <= 4 * term.stderr + 1.0), (term.mean, term.stderr)
    assert abs(term.mean.mean()) < 0.001 * term.median_signal


@pytest.mark.parametrize("rows, cols, masked", [(600, 800, False), (590, 797, True)])
def test_both_block_sizes_come_from_one_pass_with_the_two_passes_values(small, monkeypatch, rows, cols, masked):
    """The term's two block sizes (32 and 16 px) merged from one pass over the stack on 8 px blocks: the
    same term to the bit as a pass for each size, on grids that do and do not start on the same row, with
    a mask; each image read once instead of twice. Float images, whose sums change with the order, keep
    a pass per size."""
    import dataclasses

    import uvps.core.offset as off

    _, black = small
    images = np.ascontiguousarray(black.images[:, :rows, :cols])
    assert images.dtype == np.uint16
    mask = None
    if masked:
        mask = np.ones((rows, cols), bool)
        mask[100:180, 200:420] = False
    reads = []
    stats = off.image_block_stats
    monkeypatch.setattr(off, "image_block_stats", lambda *a, **kw: reads.append(a[4]) or stats(*a, **kw))

    def term(imgs, one_pass):
        reads.clear()
        with monkeypatch.context() as m:
            if not one_pass:
                m.setattr(off, "_both_grids", lambda *a, **kw: None)
            got = estimate_additive(imgs, mask=mask, saturation=65535)
        return got, sorted(reads)

    got, got_reads = term(images, True)
    ref, ref_reads = term(images, False)
    K = len(images)
    assert got_reads == [8] * K and ref_reads == [16] * K + [32] * K
    assert ref.diagnostics["block_px_compared"] == 16 and ref.diagnostics["block_px"] == 32
    for f in dataclasses.fields(off.AdditiveTerm):
        a, b = getattr(got, f.name), getattr(ref, f.name)
        assert np.array_equal(a, b) if isinstance(a, np.ndarray) else a == b, f.name
    assert np.all(np.abs(got.mean - [300.0, 200.0, 120.0]) <= 4 * got.stderr + 1.0)
    as_float = images.astype(np.float32)
    assert off._both_grids(as_float, 16, 32, None) is None
    _, float_reads = term(as_float, True)
    assert float_reads == [16] * K + [32] * K


def test_the_two_centred_grids_fall_on_the_fine_one():
    """What the one pass relies on: for blocks of b, 2b and 4b px (b a power of two) centred on any image
    side, the 4b grid starts on the 2b grid's origin or b px after it, and ends inside it."""
    from uvps.core.offset import _grid

    for b in (2, 4, 8, 16):
        for side in range(4 * b, 5001):
            Rs, _, r0, _ = _grid((side, side), 2 * b)
            Rl, _, r1, _ = _grid((side, side), 4 * b)
            assert r1 - r0 in (0, b) and r1 + 4 * b * Rl <= r0 + 2 * b * Rs, (b, side)


@pytest.mark.parametrize("grey", [False, True])
def test_one_pass_blocks_are_each_sizes_own_with_saturated_and_dark_pixels(small, grey):
    """Each size's block means and usable blocks merged from the one pass are those of a pass of its own,
    for colour and grey stacks, where a few pixels (inside one 8 px block) are saturated or black: a
    block holding any of them is left out, at both sizes."""
    import uvps.core.offset as off

    _, black = small
    images = black.images[:, :590, :797].copy()
    images[:, 40:44, 100:103] = 65535
    images[:, 300:302, 500:505] = 0
    if grey:
        images = np.ascontiguousarray(images[..., 1])
    both = off._both_grids(images, 16, 32, 65535.0)
    for blk in (16, 32):
        ref = off._channel_blocks(images, block=blk, mask=None, saturation=65535.0)
        got = off._channel_blocks(images, block=blk, mask=None, saturation=65535.0, blocks=both[blk])
        for a, b in zip(got, ref):
            np.testing.assert_array_equal(a, b)
        assert 2 <= (~ref[1]).sum() <= 4, blk     # the blocks of the saturated pixels and of the black ones


def test_grey_captures_are_measured_like_colour_ones(small):
    """A grey stack (K, M, N) gets the same block means as one channel and its black level measured:
    the grey of the per-channel levels, and none on the clean capture. (A transposed block grid for
    grey stacks once measured -300 to +280 counts on clean captures and sent estimated lamps 40 deg
    off.)"""
    from uvps.core.offset import _channel_blocks

    clean, black = small
    grey = black.images.mean(axis=-1).astype(np.float32)
    blk, ok, _, _ = _channel_blocks(grey, block=16, mask=None, saturation=None)
    ref = grey[:, 4:596, :].reshape(8, 37, 16, 50, 16).mean(axis=(2, 4), dtype=np.float64)   # centred rows
    np.testing.assert_allclose(blk[:, 0], ref, rtol=1e-6)
    term = estimate_additive(grey, saturation=None)
    assert abs(term.mean[0] - np.mean([300.0, 200.0, 120.0])) <= max(4 * term.stderr[0], 0.001 * term.median_signal)
    term0 = estimate_additive(clean.images.mean(axis=-1).astype(np.float32), saturation=None)
    assert abs(term0.mean[0]) <= max(4 * term0.stderr[0], 0.001 * term0.median_signal), (term0.mean, term0.stderr)


def test_the_measure_is_shift_equivariant(small):
    """Adding 100 counts to every image adds 100 to the measured term (the cue sees only the data)."""
    clean, _ = small
    a = estimate_additive(clean.images, saturation=65535)
    b = estimate_additive(clean.images.astype(np.float32) + 100.0, saturation=None)
    assert np.allclose(b.mean - a.mean, 100.0, atol=max(2.0, 2 * float(a.stderr.max())))


def test_stray_light_is_measured_as_its_mean():
    """Stray light (3 % of the signal, smooth, the same in every image) is measured as a constant: its
    mean over the field, within 20 %."""
    cap = make_capture(shape=(600, 800), n_lights=8, seed=5, stray_light=0.03)
    true_mean = np.asarray(cap.nuisances.info["stray_light"]["mean_counts"])
    term = estimate_additive(cap.images, saturation=65535)
    assert np.all(np.abs(term.mean - true_mean) < 0.2 * true_mean + 3 * term.stderr), (term.mean, true_mean)


def test_offset_images_subtract_on_access_without_copying():
    rng = np.random.default_rng(0)
    im = rng.integers(100, 200, (4, 40, 50, 3)).astype(np.uint16)
    co = np.zeros((3, 2, 2))
    co[:, 0, 0] = [10, 20, 30]
    co[:, 0, 1] = 5
    co[:, 1, 1] = 3
    term = AdditiveTerm(co, "estimated", (40, 50))
    view = OffsetImages(im, term)
    rr, cc = np.mgrid[0:40, 0:50]
    full = im - term.evaluate(rr, cc)[None]
    r, c = np.array([1, 5, 7]), np.array([3, 4, 40])
    assert np.allclose(view[:], full, atol=1e-3)
    assert np.allclose(view[2], full[2], atol=1e-3)
    assert np.allclose(view[1, 3:7, 2:9], full[1, 3:7, 2:9], atol=1e-3)
    assert np.allclose(view[1, 3, 2:9], full[1, 3, 2:9], atol=1e-3)
    assert np.allclose(view[:, r, c], full[:, r, c], atol=1e-3)
    assert np.allclose(np.stack(list(view)), full, atol=1e-3)
    assert view.base is im and im.dtype == np.uint16          # the stack is untouched
    grey = OffsetImages(im.mean(axis=-1), term)
    assert np.allclose(grey[:, r, c], im.mean(axis=-1)[:, r, c] - term.evaluate(r, c).mean(axis=-1), atol=1e-3)


def test_known_black_level_is_validated():
    t = known_additive([10, 20, 30], shape=(5, 5), channels=3)
    assert np.allclose(t.mean, [10, 20, 30]) and t.source == "black level"
    assert np.allclose(known_additive(7, shape=(5, 5), channels=3).mean, 7)
    with pytest.raises(UVPSInputError, match="black_level"):
        known_additive([1, 2], shape=(5, 5), channels=3)
    with pytest.raises(UVPSInputError, match="black_level"):
        known_additive(-3, shape=(5, 5), channels=1)


def test_remove_additive_uses_a_given_black_level_and_records_it(small):
    _, black = small
    cap, term, warnings = remove_additive(_capture(black.images), options=RunOptions(black_level=[300, 200, 120]))
    assert term.source == "black level" and warnings == []
    assert isinstance(cap.images, OffsetImages)
    raw = black.images[0, 10, 10].astype(float)
    assert np.allclose(cap.images[0, 10, 10], raw - [300, 200, 120])
    assert json.dumps(term.to_json())                            # run.json-ready


def test_dark_frame_or_none_removes_nothing_more(small):
    _, black = small
    for kw, src in ((dict(dark_given=True), "dark frame"), (dict(), "none")):
        opts = RunOptions() if kw else RunOptions(offset="none")
        cap, term, _ = remove_additive(_capture(black.images), options=opts, **kw)
        assert term.source == src and term.is_zero and cap.images is black.images


def test_mostly_pedestal_is_a_one_line_error(small):
    clean, _ = small
    with pytest.raises(UVPSInputError, match="mostly pedestal") as e:
        remove_additive(_capture(clean.images), options=RunOptions(black_level=float(np.median(clean.images))))
    assert "\n" not in str(e.value)


def test_tiny_images_use_smaller_blocks():
    """A 60 x 80 image has too few 16 px blocks; smaller ones are used and the error is reported."""
    cap = make_capture(shape=(60, 80), n_lights=6, seed=1, black_level=200.0)
    term = estimate_additive(cap.images, saturation=65535)
    assert term.diagnostics["block_px"] < 16
    assert np.all(np.isfinite(term.stderr)) and np.all(term.stderr > 0)


def test_a_negative_measure_is_not_added_back(small):
    """A pedestal is never negative: an image lowered by 100 counts everywhere (clipped nowhere)
    measures about -100, which is reported and not subtracted."""
    clean, _ = small
    lowered = clean.images.astype(np.float32) - 100.0
    cap, term, warnings = remove_additive(_capture(lowered), options=RunOptions())
    assert term.mean.mean() < -50 and term.diagnostics["used"] is False
    assert cap.images is lowered and warnings == []


def test_too_few_usable_blocks_is_not_measurable_and_does_not_stop_the_run(small):
    """Every block saturated in some image: nothing to measure by; the run goes on (known lights do not
    need the term) and, with lamps to estimate, says so once."""
    clean, _ = small
    images = clean.images.copy()
    images[0, :, ::8] = 65535                       # a saturated column in every block of image 0
    cap, term, warnings = remove_additive(_capture(images), options=RunOptions())
    assert cap.images is images and term.is_zero and "not measurable" in term.diagnostics["note"]
    assert len(warnings) == 1 and "could not be measured" in warnings[0]


def test_a_masked_object_on_black_is_not_taken_for_pedestal(small):
    """Half the field black and masked out (an object on a black ground): the median signal is taken
    inside the mask, and an unmeasurable term is no reason to call the images pedestal."""
    clean, _ = small
    images = clean.images.copy()
    images[:, :, 400:] = 0
    mask = np.zeros(images.shape[1:3], bool)
    mask[:, :400] = True
    cap = _capture(images)
    cap.mask = mask
    out, term, _ = remove_additive(cap, options=RunOptions())
    assert term.median_signal > 1000


def test_one_paint_is_not_measurable_and_the_run_goes_on_with_a_warning():
    """A field of one paint has no colour areas to cancel: the fit of c runs away. That is "not
    measurable" (estimated lamps: a warning saying what to give), not "mostly pedestal" (the images
    are at 28000 counts)."""
    from uvps.testing.synthetic import render_images

    cap = make_capture(shape=(240, 320), n_lights=8, seed=2)
    imgs = render_images(cap.height_um, np.full(cap.height_um.shape + (3,), 0.7), pixel_size_um=15.0,
                         light_positions_mm=cap.light_positions_mm, noise=True, dtype=np.uint16)
    term = estimate_additive(imgs, saturation=65535)
    assert term.is_zero and "too few paints" in term.diagnostics["note"]
    _, term, warnings = remove_additive(_capture(imgs), options=RunOptions())
    assert len(warnings) == 1 and "could not be measured" in warnings[0] and "dark frame" in warnings[0]


@pytest.mark.parametrize("shape,dtype", [((84, 126, 3), np.uint16), ((84, 126), np.uint16), ((84, 126, 3), np.float32)])
def test_block_stats_equal_the_numpy_statistics(shape, dtype):
    """One compiled pass gives the block means, the smallest grey and sample, and saturation, with a
    black pixel and a saturated sample planted."""
    from uvps.core.offset import block_stats

    rng = np.random.default_rng(4)
    img = rng.integers(1, 60000, shape).astype(dtype)
    img[10, 11] = 0
    img[50, 100] = 65535
    st = block_stats(img, 14, saturation=65535)
    x = img.reshape(6, 14, 9, 14, -1).astype(np.float64)
    means = x.mean(axis=(1, 3)) if img.ndim == 3 else x.mean(axis=(1, 3))[..., 0]
    if np.issubdtype(dtype, np.integer):
        np.testing.assert_array_equal(st.means, means)
    else:
        np.testing.assert_allclose(st.means, means, rtol=1e-12)
    np.testing.assert_array_equal(st.grey_min, x.sum(-1).min(axis=(1, 3)))
    np.testing.assert_array_equal(st.sample_min, x.min(axis=(1, 3, 4)))
    np.testing.assert_array_equal(st.saturated, (x >= 65535).any(axis=(1, 3, 4)))
    assert st.sample_min[0, 0] == 0 and st.saturated[3, 7] and st.saturated.sum() == 1
    assert not block_stats(img, 14).saturated.any()                  # no saturation given


@pytest.mark.parametrize("seed,bow_um", [(1, 200.0), (2, 250.0)])
def test_black_level_on_a_bowed_canvas_lies_within_its_reported_error(seed, bow_um):
    """A canvas bowed by 200-250 um across a 24 x 18 mm field and a black level of 200 counts: the
    measure's standard error holds the texture's bias (the block sizes' spread), so the true value
    lies within 2 standard errors of the grey measure (what decides whether it is subtracted) and
    within 3 in every channel (jackknife alone: 3.6 standard errors off at 1600 x 1200, seed 1)."""
    from uvps.testing.synthetic import SyntheticSpec

    cap = make_capture(SyntheticSpec(shape=(600, 800), pixel_size_um=30.0, seed=seed, n_lights=12, bow_um=bow_um,
                                     black_level=200.0))
    term = estimate_additive(cap.images, saturation=65535)
    assert term.diagnostics["block_px"] == 32 and term.diagnostics["block_px_compared"] == 16
    se = np.asarray(term.stderr)
    grey_se = float(np.sqrt(np.mean(se ** 2)))
    assert abs(float(term.mean.mean()) - 200.0) <= 2 * grey_se, (term.mean, se)
    assert np.all(np.abs(term.mean - 200.0) <= 3 * se), (term.mean, se)
    assert grey_se < 15.0                      # honest, not vacuous: 200 counts are told from 0


def test_eight_bit_input_is_not_measured_by_default_but_a_given_term_is_used():
    """Linearised JPEGs / 8-bit files carry a tone curve's remnant, no pedestal: the additive term is
    not measured unless asked (offset="measure"); a given black level beats everything."""
    import dataclasses

    from uvps.core.pipeline import RunOptions, remove_additive

    cap = make_capture(shape=(240, 320), n_lights=8, seed=4).as_capture(lights="positions")
    img = np.asarray(cap.images, dtype=np.float64)
    eight = np.clip(img / img.max() * 230 + 12, 0, 255).astype(np.uint8)       # a pedestal of 12 counts
    cap8 = dataclasses.replace(cap, images=eight, bit_depth="uint8", saturation=255.0)
    _, term, _ = remove_additive(cap8, options=RunOptions())
    assert term.source == "none" and term.is_zero and "uint8" in term.to_json()["note"]
    _, measured, _ = remove_additive(cap8, options=RunOptions(offset="measure"))
    assert measured.source == "estimated" and measured.stderr is not None
    out, given, _ = remove_additive(cap8, options=RunOptions(black_level=12))
    assert given.source == "black level" and np.allclose(given.mean, 12.0)
    assert float(np.asarray(out.images[0], np.float32).min()) >= -12.0        # subtracted on access
    # 16-bit input: measured by default
    _, sixteen, _ = remove_additive(cap, options=RunOptions())
    assert sixteen.source == "estimated"
