"""The readers' shared index check (deltar.data.sequence)."""

from __future__ import annotations

import pytest

from deltar.data.sequence import checked_index


def test_checked_index_keeps_list_indices_and_names_the_item_otherwise():
    assert [checked_index(i, 3) for i in (0, 2, -1, -3)] == [0, 2, -1, -3]
    with pytest.raises(IndexError, match="frame index 3 out of range for 3 frames"):
        checked_index(3, 3)
    with pytest.raises(IndexError, match="sample index -4 out of range for 3 samples"):
        checked_index(-4, 3, "sample")
    with pytest.raises(IndexError, match="frame index 0 out of range for 0 frames"):
        checked_index(0, 0)
