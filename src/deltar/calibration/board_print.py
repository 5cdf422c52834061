"""A printable page with a calibration board at true scale (PDF or PNG)."""

from __future__ import annotations

import math
import os
from pathlib import Path

from deltar.calibration.board import BoardSpec
from deltar.camera import strict_number
from deltar.io.atomic import atomic_path

#: Paper sizes (width, height) in millimetres, portrait.
PAPER_MM = {"a4": (210.0, 297.0), "letter": (215.9, 279.4)}
#: Blank border kept on every side of the board (most printers print to within 5 mm of
#: the edge), mm.
PAGE_MARGIN_MM = 5.0
#: Room needed under the board for the notes and the scale bar, mm; with less, the spec
#: is printed up the side margin instead.
NOTES_MM = 30.0
MM_PER_INCH = 25.4


def write_board_page(path: str | os.PathLike, spec: BoardSpec, *, paper: str = "a4",
                     dpi: int = 300, overwrite: bool = False) -> Path:
    """Write the board on one page at true scale, with its spec and a scale bar.

    The page is portrait or landscape, whichever leaves more room around the board
    (at least ``PAGE_MARGIN_MM``); the spec and how to check the print go under the
    board with a 100 mm scale bar, or up the side margin when there is no room below.
    The format follows the suffix (``.pdf``: vector page of the
    paper's exact size with the board as an image; ``.png``: ``dpi`` pixels per inch,
    the resolution stored in the file).

    Args:
        path: output ``.pdf`` or ``.png`` (written atomically).
        spec: the board.
        paper: ``"a4"`` or ``"letter"``.
        dpi: PNG resolution (and the board image's in the PDF), dots per inch.
        overwrite: replace an existing file.

    Returns:
        The written path.

    Raises:
        ValueError: unknown paper or suffix, a ``dpi`` that is not a finite number > 0,
            or a board larger than the printable area (the message names ``--target`` and
            the largest square size that fits).
    """
    if not math.isfinite(strict_number(dpi, "dpi")) or not dpi > 0:
        raise ValueError(f"dpi must be a finite number > 0 (dots per inch), got {dpi!r}")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    fmt = path.suffix.lower().lstrip(".")
    if fmt not in ("pdf", "png"):
        raise ValueError(f"--out {path}: write a .pdf or .png page")
    if paper not in PAPER_MM:
        raise ValueError(f"--paper must be one of {sorted(PAPER_MM)}, got {paper!r}")
    board_w, board_h = (1000.0 * v for v in spec.size_m)
    portrait = PAPER_MM[paper]
    # The orientation that leaves the most room around the board.
    page_w, page_h = max((portrait, portrait[::-1]),
                         key=lambda p: min(p[0] - board_w, p[1] - board_h))
    if min(page_w - board_w, page_h - board_h) < 2 * PAGE_MARGIN_MM:
        across, down = spec.squares
        fit = max(min((p[0] - 2 * PAGE_MARGIN_MM) / across, (p[1] - 2 * PAGE_MARGIN_MM) / down)
                  for p in (portrait, portrait[::-1]))
        raise ValueError(f"--target {spec.text()}: the board ({board_w:.0f} x {board_h:.0f} mm) "
                         f"does not fit on {paper} paper with {PAGE_MARGIN_MM:.0f} mm margins; "
                         f"use squares of at most {fit:.1f} mm or fewer squares")
    fig = plt.figure(figsize=(page_w / MM_PER_INCH, page_h / MM_PER_INCH), dpi=dpi)
    below = page_h - board_h - 2 * PAGE_MARGIN_MM  # room for notes under the board
    left = (page_w - board_w) / 2
    bottom = page_h - PAGE_MARGIN_MM - board_h if below >= NOTES_MM else (page_h - board_h) / 2
    ax = fig.add_axes((left / page_w, bottom / page_h, board_w / page_w, board_h / page_h))
    pixels = max(32, round(spec.square_m * 1000 / MM_PER_INCH * dpi))
    ax.imshow(spec.texture(pixels), cmap="gray", vmin=0, vmax=255, interpolation="nearest",
              aspect="auto", extent=(0, 1, 1, 0))
    ax.set_axis_off()
    squares = (f"{spec.squares[0]} x {spec.squares[1]} squares of {1000 * spec.square_m:g} mm"
               + (f", {1000 * spec.marker_m:g} mm markers ({spec.dictionary})"
                  if spec.kind == "charuco" else f" ({spec.cols} x {spec.rows} inner corners)"))
    if below >= NOTES_MM:
        bar_mm = 100.0 if board_w >= 100 else 50.0
        bar_y = (bottom - 8.0) / page_h
        fig.add_artist(plt.Line2D([left / page_w, (left + bar_mm) / page_w], [bar_y, bar_y],
                                  color="black", linewidth=1.5))
        fig.text(left / page_w, bar_y - 3.0 / page_h, f"{bar_mm:.0f} mm (check with a ruler)",
                 fontsize=8, va="top")
        lines = [f"deltar calibration board: --target {spec.text()}", squares,
                 "Print at 100 % / actual size (no 'fit to page'); if the bar or a square "
                 "measures otherwise, give the measured square size in --target.",
                 "Fix the sheet flat on a wall, door or table that fills the ToF sensor's "
                 "view."]
        fig.text(left / page_w, bar_y - 10.0 / page_h, "\n".join(lines), fontsize=8, va="top",
                 linespacing=1.6)
    else:  # little room: the spec runs up the side margin
        lines = [f"--target {spec.text()}",
                 f"{squares}; print at 100 % (no 'fit to page'), measure a square"]
        fig.text((left + board_w + (page_w - left - board_w) / 2) / page_w, 0.5,
                 "\n".join(lines), rotation=90, fontsize=5.5, ha="center", va="center")
    with atomic_path(path, overwrite=overwrite) as tmp:
        fig.savefig(tmp, format=fmt, dpi=dpi)
    plt.close(fig)
    return path
