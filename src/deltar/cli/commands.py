"""Imports every command module so each registers its commands on the app.

Command modules import heavy dependencies (torch, timm) inside the command functions,
so ``deltar --help`` stays fast.
"""
import deltar.cli.simulate  # noqa: F401
from deltar.cli import evaluate  # noqa: F401
from deltar.cli import calibrate  # noqa: F401
from deltar.cli import demo  # noqa: F401
from deltar.cli import train  # noqa: F401
from deltar.cli import predict  # noqa: F401
from deltar.cli import models  # noqa: F401
