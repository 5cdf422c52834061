"""Imports every command module so each registers its commands on the app.

Command modules import heavy dependencies (torch, timm) inside the command functions,
so ``deltar --help`` stays fast.
"""
import deltar.cli.simulate  # noqa: F401
