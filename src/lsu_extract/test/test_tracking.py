"""The fast paths of the tracking search against their straightforward forms (independent numpy)."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from lsu_extract.signal import LaserSignal
from lsu_extract.tracking import coarse_track, interpolate_track, row_candidates


@settings(max_examples=60, deadline=None)
@given(height=st.integers(1, 120), step=st.integers(1, 16), seed=st.integers(0, 2 ** 32 - 1))
def test_coarse_track_covers_the_rows_near_found_coarse_rows_like_the_general_rule(height, step, seed):
    rng = np.random.default_rng(seed)
    coarse_rows = np.arange(min(step // 2, height - 1), height, step)
    column = np.where(rng.random(coarse_rows.size) < 0.6, rng.integers(0, 500, coarse_rows.size), -1)
    rows, guess = coarse_track(height, coarse_rows, column, step)
    ok = column >= 0
    # the rule spelled out: a row is tracked when a found coarse row lies within `step` rows of it
    all_rows = np.arange(height)
    near = (np.abs(all_rows[:, None] - coarse_rows[ok][None, :]) <= step).any(axis=1)
    np.testing.assert_array_equal(rows, all_rows[near])
    expected = interpolate_track(all_rows.astype(float), coarse_rows[ok].astype(float), column[ok].astype(float), step)
    np.testing.assert_allclose(guess, expected[near])


def test_clipped_row_signal_is_red_minus_the_brighter_other_channel_floored_at_zero():
    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, (20, 50, 3), dtype=np.uint8)
    sig = LaserSignal(image)
    b, g, r = (image[..., k].astype(int) for k in range(3))
    # the brighter of green and blue, unless it has clipped (255): then the other one
    other = np.where(np.maximum(g, b) == 255, np.minimum(g, b), np.maximum(g, b))
    assert np.count_nonzero(other != np.maximum(g, b)) > 0  # the frame holds clipped pixels
    expected = np.clip(r - other, 0, 255)
    np.testing.assert_array_equal(sig.rows_clipped(slice(1, 20, 4)), expected[1::4])
    np.testing.assert_array_equal(sig.rows(np.array([2, 7])), (r - other)[[2, 7]])
    signal, red, first = sig.windows(np.array([3, 9]), np.array([5, 20]), 12)
    np.testing.assert_array_equal(signal, np.stack([(r - other)[3, 5:17], (r - other)[9, 20:32]]))
    cols, _ = sig.window_columns(np.array([3 * 50 + 5, 9 * 50 + 20]), 12)
    np.testing.assert_array_equal(cols.T, signal)


def test_signal_with_a_laser_off_frame_is_the_red_rise_less_the_larger_green_or_blue_rise():
    rng = np.random.default_rng(4)
    image = rng.integers(0, 256, (20, 50, 3), dtype=np.uint8)
    texture = rng.integers(0, 256, image.shape, dtype=np.uint8)
    rise = image.astype(int) - texture.astype(int)
    expected = rise[..., 2] - np.maximum(np.maximum(rise[..., 1], rise[..., 0]), 0)
    sig = LaserSignal(image, texture)
    np.testing.assert_array_equal(sig.rows_clipped(slice(None)), np.clip(expected, 0, 255))
    np.testing.assert_array_equal(sig.rows(np.array([2, 7])), expected[[2, 7]])
    signal, red = sig.window_columns(np.array([3 * 50 + 4, 11 * 50 + 30]), 9)  # rows 3 and 11
    np.testing.assert_array_equal(signal.T, np.stack([expected[3, 4:13], expected[11, 30:39]]))
    np.testing.assert_array_equal(red.T, np.stack([image[3, 4:13, 2], image[11, 30:39, 2]]))

@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), mono=st.booleans(), every=st.integers(0, 5))
def test_coarse_rows_with_a_laser_off_frame_share_their_planes_and_keep_both_signals(seed, mono, every):
    # one gather and split per frame (`rows_laser_off`) gives the clipped signal of the rows and the exact
    # signal of every few of them, as the definitions in numpy (and the separate methods) give them
    rng = np.random.default_rng(seed)
    shape = (int(rng.integers(1, 40)), int(rng.integers(2, 60)))
    image = rng.integers(0, 256, shape if mono else (*shape, 3), dtype=np.uint8)
    texture = rng.integers(0, 256, image.shape, dtype=np.uint8)
    rise = image.astype(int) - texture.astype(int)
    expected = rise if mono else rise[..., 2] - np.maximum(np.maximum(rise[..., 1], rise[..., 0]), 0)
    rows = np.sort(rng.choice(shape[0], int(rng.integers(0, shape[0] + 1)), replace=False))
    sig = LaserSignal(image, texture)
    clipped, exact = sig.rows_laser_off(rows, every)
    np.testing.assert_array_equal(clipped, np.clip(expected[rows], 0, 255))
    assert clipped.dtype == np.uint8
    if every == 0:
        assert exact is None
    else:
        assert exact is not None and exact.dtype == np.int16
        np.testing.assert_array_equal(exact, expected[rows[::every]])
        np.testing.assert_array_equal(exact, sig.rows(rows[::every]))
    np.testing.assert_array_equal(sig.rows_clipped(rows), clipped)


def test_rows_dark_in_every_channel_cannot_hold_the_laser():
    image = np.zeros((4, 30, 3), np.uint8)
    image[1, 5] = (0, 0, 40)   # a red pixel above the contrast
    image[2, 9] = (35, 0, 0)   # bright, but not red: the cheap test keeps it (weaker, never wrong)
    image[3, 3] = (0, 0, 29)   # red, below the contrast
    sig = LaserSignal(image)
    assert sig.may_hold_laser(np.arange(4), 30.0).tolist() == [False, True, True, False]


def test_with_a_laser_off_frame_rows_that_do_not_rise_over_it_cannot_hold_the_laser():
    from lsu_extract.signal import RISE_MARGIN

    texture = np.full((4, 30, 3), 120, np.uint8)      # lit skin in every row
    image = texture.copy()
    image[1, 5, 2] += 25                              # red rises 25 DN: within RISE_MARGIN of a 30 DN contrast
    image[2, 9, 0] += 21                              # blue rises (another channel: weaker, never wrong)
    image[3, 3, 2] += 15                              # red rises, too little
    assert 15 < RISE_MARGIN * 30.0 <= 21
    sig = LaserSignal(image, texture)
    assert sig.may_hold_laser(np.arange(4), 30.0).tolist() == [False, True, True, False]
    assert LaserSignal(image).may_hold_laser(np.arange(4), 30.0).tolist() == [True] * 4  # bright: all searched


def test_row_candidates_agree_on_float_and_clipped_signals_where_the_signal_is_positive():
    rng = np.random.default_rng(5)
    rows = rng.integers(0, 20, (12, 200)).astype(np.float32)
    rows[np.arange(12), rng.integers(0, 200, 12)] += 120.0  # a laser peak per row
    rows[:6, 150] += 90.0                                  # and a reflection in half of them
    a = row_candidates(rows, np.arange(12), 5, 30.0)
    b = row_candidates(rows.astype(np.uint8), np.arange(12), 5, 30.0)
    np.testing.assert_array_equal(a.first, b.first)
    np.testing.assert_array_equal(a.second, b.second)
    np.testing.assert_allclose(a.first_contrast, b.first_contrast, rtol=1e-5)
    # second peaks: the brightest value outside +-5 px of the first, found by brute force
    for i in range(12):
        outside = np.abs(np.arange(200) - a.first[i]) > 5
        assert rows[i, a.second[i]] == rows[i][outside].max()


@settings(max_examples=60, deadline=None)
@given(rows=st.integers(1, 40), n=st.integers(1, 300), seed=st.integers(0, 2 ** 32 - 1))
def test_column_peak_search_is_argmax_over_axis_0_first_on_ties(rows, n, seed):
    from lsu_extract.extractor import _peak_search, _peak_search_layout

    rng = np.random.default_rng(seed)
    values = rng.integers(-255, 256, (rows, n)).astype(np.int16)
    values[:, ::3] = values[0, ::3]  # ties: the first row must win
    codes, bits, offset, interior = _peak_search_layout(rows, n, rows // 2)
    flat = _peak_search(values, codes, bits)
    j = np.argmax(values, axis=0)
    np.testing.assert_array_equal(flat, j * n + np.arange(n))
    np.testing.assert_array_equal(offset[flat], j - rows // 2)
    np.testing.assert_array_equal(interior[flat], (j > 0) & (j < rows - 1))


def test_strong_only_keeps_exactly_the_rows_with_a_peak_above_the_contrast_and_decides_the_same():
    from lsu_extract.tracking import decide

    rng = np.random.default_rng(11)
    rows = rng.integers(0, 25, (40, 160)).astype(np.float32)  # lit skin without the laser
    laser = np.zeros(40, bool)
    laser[[3, 4, 5, 6, 20, 21, 33]] = True
    cols = rng.integers(10, 150, 40)
    rows[laser, cols[laser]] += 100.0
    rows[[4, 21], 100] += 80.0  # competing reflections in two laser rows
    index = np.arange(100, 140)  # image row numbers of the searched rows
    every = row_candidates(rows, index, 4, 30.0)
    strong = row_candidates(rows, index, 4, 30.0, strong_only=True)
    # independent truth: a row is strong when its maximum stands 30 above its mean
    truth = rows.max(axis=1) - rows.mean(axis=1) >= 30.0
    assert truth.tolist() == laser.tolist()
    np.testing.assert_array_equal(strong.rows, index[truth])
    for name in ("first", "second"):
        np.testing.assert_array_equal(getattr(strong, name), getattr(every, name)[truth])
    ref_rows, ref_cols = np.array([99]), np.array([float(cols[3])])
    d_all = decide(every, 30.0, 0.6, 8, ref_rows, ref_cols, 16)
    d_strong = decide(strong, 30.0, 0.6, 8, ref_rows, ref_cols, 16)
    np.testing.assert_array_equal(d_strong.column, d_all.column[truth])
    assert (d_all.column[~truth] < 0).all() and not d_all.ambiguous[~truth].any()
    assert d_strong.ambiguous.sum() == d_all.ambiguous.sum()
    nothing = row_candidates(rows[~laser], index[~laser], 4, 30.0, strong_only=True)
    assert nothing.rows.size == nothing.first.size == 0
    # weak rows the minority (searched along with the strong ones, then dropped): the same strong rows
    few_weak = np.sort(np.r_[laser.nonzero()[0], (~laser).nonzero()[0][:3]])
    mostly = row_candidates(rows[few_weak], index[few_weak], 4, 30.0, strong_only=True)
    np.testing.assert_array_equal(mostly.rows, index[truth])
    for name in ("first", "second", "first_contrast", "second_contrast"):
        np.testing.assert_array_equal(getattr(mostly, name), getattr(every, name)[truth])


def _decide_row_by_row(rows, first, second, first_contrast, second_contrast, min_contrast, ambiguity_ratio,
                       window_px, ref_rows, ref_cols, max_gap_rows):
    """`decide`'s rule written out row by row in plain Python: the reference of a row is the first known
    row at distance 1, 2, ... up to max_gap_rows, the one above first; up to 4 passes."""
    n = len(rows)
    strong = [first_contrast[i] >= min_contrast for i in range(n)]
    double = [strong[i] and second_contrast[i] >= max(0.25 * first_contrast[i], min_contrast) for i in range(n)]
    competing = [double[i] and second_contrast[i] >= ambiguity_ratio * first_contrast[i] for i in range(n)]
    column = [int(first[i]) if strong[i] and not double[i] else -1 for i in range(n)]
    known = {int(r): float(c) for r, c in zip(ref_rows, ref_cols)}
    known.update({int(rows[i]): float(column[i]) for i in range(n) if column[i] >= 0})
    for _ in range(4):
        picks = {}
        for i in range(n):
            if not double[i] or column[i] >= 0:
                continue
            ref = next((known[r] for d in range(1, max_gap_rows + 1) for r in (rows[i] - d, rows[i] + d)
                        if r in known), None)
            if ref is None:
                continue
            near_first, near_second = abs(first[i] - ref) <= window_px, abs(second[i] - ref) <= window_px
            if near_first != near_second:
                picks[i] = int(first[i] if near_first else second[i])
        if not picks:
            break
        for i, pick in picks.items():
            column[i] = pick
            known[int(rows[i])] = float(pick)
    ambiguous = [double[i] and column[i] < 0 and competing[i] for i in range(n)]
    column = [int(first[i]) if double[i] and column[i] < 0 and not competing[i] else column[i] for i in range(n)]
    return column, ambiguous


@settings(max_examples=80, deadline=None)
@given(seed=st.integers(0, 2 ** 32 - 1), max_gap_rows=st.integers(1, 20), with_refs=st.booleans())
def test_decide_follows_its_rule_row_by_row(seed, max_gap_rows, with_refs):
    from lsu_extract.tracking import RowCandidates, decide

    rng = np.random.default_rng(seed)
    # a line drifting across 120 rows, with a reflection 15-40 px away in most rows and gaps between
    # references at every distance, so that ties, the gap limit and several passes all occur
    all_rows = np.arange(120)
    line = np.rint(60 + np.cumsum(rng.integers(-2, 3, 120))).astype(np.int64)
    searched = np.sort(rng.choice(120, 80, replace=False))
    others = np.setdiff1d(all_rows, searched)
    ref_rows = np.sort(rng.choice(others, rng.integers(1, others.size), replace=False)) if with_refs \
        else np.zeros(0, np.int64)
    ref_cols = line[ref_rows].astype(np.float32) + rng.uniform(-1, 1, ref_rows.size).astype(np.float32)
    offset = rng.choice([-1, 1], searched.size) * rng.integers(15, 40, searched.size)
    # a column is >= 0 (-1 means "no second peak"): a reflection that would fall left of the image lies right
    reflection = np.where(line[searched] + offset >= 0, line[searched] + offset, line[searched] - offset)
    swap = rng.random(searched.size) < 0.5  # the reflection is the stronger peak in half the rows
    first, second = np.where(swap, reflection, line[searched]), np.where(swap, line[searched], reflection)
    # whole numbers and a ratio of 0.5: the thresholds are exact in float32 and in Python's floats alike
    first_contrast = rng.integers(20, 100, searched.size).astype(np.float32)
    second_contrast = np.floor(first_contrast * rng.uniform(0.0, 1.0, searched.size)).astype(np.float32)
    c = RowCandidates(rows=searched, first=first, second=second, first_contrast=first_contrast,
                      second_contrast=second_contrast)
    got = decide(c, 30.0, 0.5, 8, ref_rows, ref_cols, max_gap_rows)
    column, ambiguous = _decide_row_by_row(searched.tolist(), first.tolist(), second.tolist(), first_contrast.tolist(),
                                           second_contrast.tolist(), 30.0, 0.5, 8, ref_rows.tolist(),
                                           ref_cols.tolist(), max_gap_rows)
    assert got.column.tolist() == column
    assert got.ambiguous.tolist() == ambiguous
