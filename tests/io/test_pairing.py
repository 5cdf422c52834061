"""One reading per image: the nearest kept, the others counted in one warning."""

from __future__ import annotations

import warnings

import pytest

from deltar.io.pairing import one_per_image


def test_the_nearest_reading_of_each_image_is_kept_in_order():
    # (image, distance to it): image "a" has three readings, "b" one.
    pairs = [("a", 0.012), ("a", 0.004), ("b", 0.001), ("a", 0.004)]
    with pytest.warns(UserWarning, match=r"^src: 2 of 4 ToF frames share a colour image "
                      r"with a ToF frame nearer to it in time and are left out \(one ToF "
                      r"frame per image\)$"):
        kept = one_per_image(pairs, lambda p: p[0], lambda p: p[1], "src", what="ToF frame")
    assert kept == [pairs[1], pairs[2]]  # the first of a tie


def test_one_reading_per_image_keeps_all_without_a_warning():
    pairs = [("a", 0.01), ("b", 0.02)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert one_per_image(pairs, lambda p: p[0], lambda p: p[1], "src") == pairs
