"""Input / held-out selection: the rule on a known n, held-out frames never inputs, extrapolation."""

from __future__ import annotations

import pytest

from canonical_core.eval.protocol import (
    extrapolation_split,
    interpolation_split,
    nearest_free,
    spread,
    stability_inputs,
)


def test_heldout_rule_on_the_shelf_length():
    split = interpolation_split(50, [2, 4, 8, 16])
    assert split.inputs[2] == (0, 49)
    assert split.inputs[4] == (0, 16, 33, 49)
    assert split.inputs[8] == (0, 7, 14, 21, 28, 35, 42, 49)
    assert split.inputs[16] == (0, 3, 7, 10, 13, 16, 20, 23, 26, 29, 33, 36, 39, 42, 46, 49)
    # targets linspace(2, 47, 10) = 2, 7, 12, ..., 47; 7 and 42 are inputs: 6/8 and 41/43 tie -> lower
    assert split.heldout == (2, 6, 12, 17, 22, 27, 32, 37, 41, 47)


def test_nearest_free_ties_go_to_the_lower_position_and_skip_taken_ones():
    assert nearest_free([5.0], {5}, 10) == (4,)
    assert nearest_free([5.5], set(), 10) == (5,)
    assert nearest_free([5.0, 5.0, 5.0], set(), 10) == (5, 4, 6)
    with pytest.raises(ValueError, match="no unused frame"):
        nearest_free([1.0], {0, 1, 2}, 3)


@pytest.mark.parametrize("n", [12, 20, 23, 37, 50, 64, 200])
@pytest.mark.parametrize("views", [[2], [2, 4], [2, 4, 8], [3, 5, 7]])
def test_heldout_frames_are_never_inputs(n, views):
    try:
        split = interpolation_split(n, views)
    except ValueError as exc:
        assert "views" in str(exc)  # too few frames left: refused, naming the argument
        return
    assert len(split.heldout) == len(set(split.heldout)) == 10
    for v in views:
        assert len(split.inputs[v]) == v and split.inputs[v] == spread(n, v)
        assert not set(split.inputs[v]) & set(split.heldout)
    assert all(0 <= p < n for p in split.heldout)


def test_bad_arguments_name_the_argument():
    with pytest.raises(ValueError, match="views"):
        interpolation_split(10, [16])
    with pytest.raises(ValueError, match="views"):
        interpolation_split(50, [])
    with pytest.raises(ValueError, match="views"):
        interpolation_split(14, [2, 4, 8])  # 10 inputs, 4 frames left for 10 held-out ones
    with pytest.raises(ValueError, match="n"):
        interpolation_split(5, [2])


def test_extrapolation_targets_span_about_20_percent_more_than_the_inputs():
    split = interpolation_split(50, [2, 4, 8, 16])
    extra = extrapolation_split(50, [2, 4, 8, 16], split.heldout)
    assert extra is not None and extra.heldout == split.heldout
    for v, inputs in extra.inputs.items():
        assert len(inputs) == v and not set(inputs) & set(split.heldout)
        assert min(split.heldout) < inputs[0] and inputs[-1] < max(split.heldout)
        assert extra.span_ratio(v) == pytest.approx(1.2, abs=0.05)
    assert extrapolation_split(24, [16], interpolation_split(24, [2]).heldout) is None  # not enough free frames


def test_stability_inputs_avoid_heldout_frames():
    split = interpolation_split(50, [2, 4, 8, 16])
    inputs = stability_inputs(50, split.heldout)
    assert sorted(inputs) == list(range(2, 13))
    for v, positions in inputs.items():
        assert len(set(positions)) == v and not set(positions) & set(split.heldout)
    assert inputs[4] == split.inputs[4] and inputs[8] == split.inputs[8]


def test_stability_counts_given_must_fit_and_the_default_keeps_those_that_do():
    heldout = interpolation_split(14, [2]).heldout  # 10 held out, 4 frames free
    assert sorted(stability_inputs(14, heldout)) == [2, 3, 4]
    assert sorted(stability_inputs(14, heldout, [3, 2])) == [2, 3]
    with pytest.raises(ValueError, match=r"stability_views: \[5\] do not fit"):
        stability_inputs(14, heldout, [2, 5])
    with pytest.raises(ValueError, match=r"stability_views: \[0\] do not fit"):
        stability_inputs(14, heldout, [0, 2])
