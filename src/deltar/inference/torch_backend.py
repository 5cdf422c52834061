"""The PyTorch backend's network call, numpy arrays in and out.

:meth:`~deltar.inference.estimator.DepthEstimator.run_network` calls
:func:`run_torch_network` for a PyTorch model (and onnxruntime's session for an ONNX
one), so both backends take and give the same arrays.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    import torch


def run_torch_network(model: torch.nn.Module, device: torch.device, dtype: torch.dtype,
                      arrays: Sequence[np.ndarray | None], flip_average: bool = False
                      ) -> tuple[np.ndarray, np.ndarray]:
    """Run a DELTAR-style network on numpy inputs in inference mode.

    Args:
        model: the network (eval mode, on ``device`` in ``dtype``), called as
            ``model(image, hypotheses, zone_rects, zone_valid, **flags)``.
        device, dtype: where and in what precision it runs.
        arrays: (image (B, 3, h, w) float32 normalised, hypotheses (B, Z, K) metres,
            zone_rects (B, Z, 4) pixels of the input, zone_valid (B, Z) bool,
            zone_no_target (B, Z) bool or None, zone_targets (B, Z, T, 2) or None). The
            flags and targets are passed only to a model that reads them
            (``uses_no_target`` / ``uses_targets``), so a user's own module keeps the
            four-input call.
        flip_average: also run the mirrored inputs and average
            (:func:`~deltar.inference.flip.flip_averaged`).

    Returns:
        (depth, uncertainty), each (B, 1, h/2, w/2) float32 numpy arrays in metres.
    """
    import torch

    def run(image: Any, hypotheses: Any, zone_rects: Any, zone_valid: Any,
            zone_no_target: Any = None, zone_targets: Any = None) -> tuple[Any, Any]:
        flags = {"zone_no_target": zone_no_target} if (
            zone_no_target is not None and getattr(model, "uses_no_target", False)) else {}
        if zone_targets is not None and getattr(model, "uses_targets", False):
            flags["zone_targets"] = zone_targets.to(dtype)
        with torch.inference_mode():
            out = model(image.to(dtype), hypotheses.to(dtype), zone_rects, zone_valid, **flags)
        return out["depth"].float(), out["uncertainty"].float()

    tensors = [None if array is None else torch.from_numpy(np.asarray(array)).to(device)
               for array in arrays]
    if flip_average:
        from deltar.inference.flip import flip_averaged

        depth, uncertainty = flip_averaged(run, *tensors)
    else:
        depth, uncertainty = run(*tensors)
    return depth.cpu().numpy(), uncertainty.cpu().numpy()
