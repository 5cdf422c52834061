"""The network's input contract, defined once: a leaf every package may import.

Weights carry their own contract in their config (``image_mean`` / ``image_std``,
``hypothesis_sampling``, ``design_size``; see :mod:`deltar.models.checkpoint`); these
are the values it can take and the defaults new models start from.
"""

from __future__ import annotations

#: The network's input height and width must be multiples of this (pixels): the image
#: encoder's coarsest stride.
SIZE_DIVISOR = 32
#: ImageNet statistics (RGB, images in [0, 1]): the release's input normalisation.
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
#: How per-zone depth hypotheses are drawn from a zone's (mean, sigma): "icdf" (the
#: release: evenly spaced quantiles of the Gaussian) or "uniform" (random draws).
HYPOTHESIS_SAMPLINGS = ("icdf", "uniform")
