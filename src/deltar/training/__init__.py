"""Training DELTAR with Lightning: configuration, data module, Lightning module, runs.

Importing this package needs the ``train`` extra (``lightning``); the configuration
schema (:mod:`deltar.training.config`) needs only PyYAML.
"""

from deltar.training.config import TrainConfig, load_config

__all__ = ["TrainConfig", "load_config"]
