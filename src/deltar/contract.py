"""The network's input contract, defined once: a leaf every package may import.

Weights carry their own contract in their config (``image_mean`` / ``image_std``,
``hypothesis_sampling``, ``design_size``; see :mod:`deltar.models.checkpoint`); these
are the values it can take and the defaults new models start from; and the one image
normaliser (:func:`normalise_image`) that maps camera images onto the contract.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

#: The network's input height and width must be multiples of this (pixels): the image
#: encoder's coarsest stride.
SIZE_DIVISOR = 32
#: ImageNet statistics (RGB, images in [0, 1]): the release's input normalisation.
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
#: How per-zone depth hypotheses are drawn from a zone's (mean, sigma): "icdf" (the
#: release: evenly spaced quantiles of the Gaussian) or "uniform" (random draws).
HYPOTHESIS_SAMPLINGS = ("icdf", "uniform")


def normalise_image(image: np.ndarray, mean: Sequence[float] = IMAGENET_MEAN,
                    std: Sequence[float] = IMAGENET_STD) -> np.ndarray:
    """An RGB image as the network's input: ``(rgb - mean) / std`` with rgb in [0, 1].

    The release's formula, in float32 and in its order (divide by 255, subtract the mean,
    divide by the std). Training, the parity checks and the tests use it; the
    estimator's batched form (:func:`deltar.inference.preprocess.normalise_images`)
    resizes as it normalises and is tested against it.

    Args:
        image: (H, W, 3) RGB, uint8 (0-255) or float in [0, 1] (e.g. after augmentation).
        mean, std: per RGB channel, the network's input contract
            (``model.config["image_mean"]`` / ``["image_std"]``); ImageNet's by default.

    Returns:
        (3, H, W) float32.
    """
    image = np.asarray(image)
    if image.dtype == np.uint8:
        image = image.astype(np.float32) / np.float32(255.0)
    mean = np.asarray(mean, dtype=np.float32)
    std = np.asarray(std, dtype=np.float32)
    return ((image - mean) / std).transpose(2, 0, 1).astype(np.float32)
