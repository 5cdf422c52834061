"""Imports every command module so each registers its commands on the app.

Command modules import heavy dependencies (torch, timm) inside the command functions,
so ``deltar --help`` stays fast.
"""

from deltar.cli import (  # noqa: F401
    board,
    calibrate,
    demo,
    evaluate,
    mapping,
    models,
    predict,
    simulate,
    train,
)
