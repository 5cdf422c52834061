"""Deprecated alias: the wall test moved to :mod:`deltar.evaluation.wall_test` and its
flat-wall scenes to :mod:`deltar.data.flat_wall`.

Each name is forwarded on first use with a ``DeprecationWarning``; nothing is imported
when this module is (it sits below :mod:`deltar.evaluation` in the package layering).
"""

from __future__ import annotations

import warnings

_MOVED = {"flat_wall_frame": "deltar.data.flat_wall", "FlatWallSource": "deltar.data.flat_wall",
          "WallResult": "deltar.evaluation.wall_test", "METHODS": "deltar.evaluation.wall_test",
          "evaluate_recording": "deltar.evaluation.wall_test",
          "wall_test": "deltar.evaluation.wall_test",
          "write_results": "deltar.evaluation.wall_test"}


def __getattr__(name: str):
    if name not in _MOVED:
        raise AttributeError(f"module 'deltar.inference.wall_test' has no attribute {name!r}")
    warnings.warn(f"deltar.inference.wall_test.{name} moved to {_MOVED[name]}.{name}",
                  DeprecationWarning, stacklevel=2)
    if _MOVED[name] == "deltar.data.flat_wall":
        from deltar.data import flat_wall as module
    else:
        # The one import against the layering (inference below evaluation), listed as a
        # deprecated alias in tests/test_architecture.py; remove with this module.
        from deltar.evaluation import wall_test as module
    return getattr(module, name)
