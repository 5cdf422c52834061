"""From a real (or simulated) sensor to a depth map: estimator, outputs, record/replay.

Torch is imported only inside functions, so importing this package stays light.
"""
