"""The printable board page: its arguments are checked before anything is drawn."""

from __future__ import annotations

import pytest

from deltar.calibration.board import BoardSpec
from deltar.calibration.board_print import write_board_page


@pytest.mark.parametrize("dpi", [float("nan"), float("inf"), 0, -300, "300"])
def test_a_dpi_that_is_not_a_positive_finite_number_is_refused_naming_it(tmp_path, dpi):
    spec = BoardSpec("checkerboard", 9, 6, 0.025)
    with pytest.raises(ValueError, match=r"^dpi must be (a finite number > 0|a number)"):
        write_board_page(tmp_path / "board.png", spec, dpi=dpi)
    assert not (tmp_path / "board.png").exists()


def test_a_page_is_written_at_a_valid_dpi(tmp_path):
    pytest.importorskip("matplotlib")
    page = write_board_page(tmp_path / "board.png", BoardSpec("checkerboard", 9, 6, 0.025),
                            dpi=72)
    assert page.stat().st_size > 0
