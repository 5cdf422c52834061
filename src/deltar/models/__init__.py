"""The DELTAR network in plain PyTorch: presets, official-weight loading, loss."""

from deltar.models.losses import scaled_si_loss
from deltar.models.network import DeltarNet
from deltar.models.official import LoadReport, load_official_weights
from deltar.models.presets import ABLATIONS, PRESETS, create_model, list_presets

__all__ = [
    "ABLATIONS",
    "PRESETS",
    "DeltarNet",
    "LoadReport",
    "create_model",
    "list_presets",
    "load_official_weights",
    "scaled_si_loss",
]
