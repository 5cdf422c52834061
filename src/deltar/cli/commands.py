"""The one place that registers the ``deltar`` commands: (name, function) pairs.

Command modules define plain functions with typer options and never import the app;
:mod:`deltar.cli.main` registers these on it. Each imports its heavy dependencies (torch,
timm) inside the command function, so ``deltar --help`` stays fast.
"""

from __future__ import annotations

from collections.abc import Callable

from deltar.cli import (
    board,
    calibrate,
    capture,
    demo,
    evaluate,
    export,
    mapping,
    models,
    predict,
    simulate,
    train,
)

#: Every command, in the order ``deltar --help`` lists them.
COMMANDS: tuple[tuple[str, Callable[..., None]], ...] = (
    ("calibration-board", board.calibration_board_command),
    ("check-calibration", board.check_calibration_command),
    ("calibrate", calibrate.calibrate_command),
    ("demo", demo.demo),
    ("evaluate", evaluate.evaluate),
    ("map", mapping.map_command),
    ("check-official", models.check_official_command),
    ("bench", models.bench_command),
    ("predict", predict.predict_command),
    ("record", capture.record_command),
    ("replay", capture.replay_command),
    ("wall-test", evaluate.wall_test_command),
    ("export", export.export_command),
    ("simulate", simulate.simulate_command),
    ("train", train.train_command),
    ("fit-uncertainty", train.fit_uncertainty_command),
)
