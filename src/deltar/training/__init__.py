"""Training DELTAR with Lightning: configuration, data module, Lightning module, runs.

Importing this package needs the ``train`` extra (``lightning``); the configuration
schema (:mod:`deltar.training.config`) and its loading
(:mod:`deltar.training.config_loading`) need only PyYAML.
"""

from deltar.training.config import TrainConfig
from deltar.training.config_loading import load_config

__all__ = ["TrainConfig", "load_config"]
