"""Progress lines for logs: count, rate and time left, rate-limited."""

from __future__ import annotations

from deltar.cli.progress import ProgressReport


def test_progress_lines_have_count_rate_and_eta(capsys, monkeypatch):
    monkeypatch.setenv("DELTAR_PROGRESS_SECONDS", "0")
    with ProgressReport("predicting", total=3, terminal=False) as progress:
        for _ in range(3):
            progress.advance()
    lines = capsys.readouterr().out.splitlines()
    assert [line.split(",")[0] for line in lines] == ["predicting: 1/3 frames",
                                                      "predicting: 2/3 frames",
                                                      "predicting: 3/3 frames"]
    assert "frames/s" in lines[0] and "ETA" in lines[0] and "done in" in lines[-1]


def test_progress_lines_are_rate_limited(capsys, monkeypatch):
    monkeypatch.setenv("DELTAR_PROGRESS_SECONDS", "3600")
    with ProgressReport("simulating", total=50, terminal=False) as progress:
        for _ in range(50):
            progress.advance()
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 1 and lines[0].startswith("simulating: 50/50 frames")


def test_progress_total_can_be_set_once_known(capsys, monkeypatch):
    monkeypatch.setenv("DELTAR_PROGRESS_SECONDS", "0")
    with ProgressReport("fitting", terminal=False) as progress:
        progress.advance()
        progress.set_total(2)
        progress.advance()
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("fitting: 1 frames") and "ETA" not in lines[0]
    assert lines[-1].startswith("fitting: 2/2 frames") and "done in" in lines[-1]


def test_tables_printed_to_a_log_keep_every_cell(capsys, monkeypatch):
    """Off a terminal rich would cut tables to 80 columns; table_console does not."""
    from rich.table import Table

    from deltar.cli.progress import LOG_WIDTH, table_console

    monkeypatch.delenv("COLUMNS", raising=False)
    # CI runners often force colour, which rich takes for a terminal: still a log here.
    monkeypatch.setenv("FORCE_COLOR", "1")
    monkeypatch.setenv("TTY_COMPATIBLE", "1")
    table = Table(title="methods")
    for header in ("method", "δ1", "δ2", "δ3", "REL", "RMSE", "log10", "≤1σ", "≤2σ", "s/frame"):
        table.add_column(header)
    table.add_row("model:deltar_select_default", *(f"{v:.4f}" for v in range(9)))
    table.add_row("joint_bilateral+far", *(f"{v:.4f}" for v in range(9)))
    console = table_console()
    assert console.width == LOG_WIDTH
    console.print(table)
    out = capsys.readouterr().out
    assert "…" not in out
    assert "model:deltar_select_default" in out and "joint_bilateral+far" in out
    monkeypatch.setenv("COLUMNS", "60")  # the user's own width is kept
    assert table_console().width == 60
    monkeypatch.setenv("COLUMNS", "")  # not a width: the log's
    assert table_console().width == LOG_WIDTH
