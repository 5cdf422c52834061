"""deltar: dense metric depth from an RGB camera and a multi-zone time-of-flight sensor.

Implements DELTAR (Li et al., ECCV 2022) end to end: sensor model and simulator,
calibration, the network, training, evaluation, export and inference.
"""

__version__ = "0.1.0"
