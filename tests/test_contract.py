"""The input contract: its constants agree with the network and the sampler that use them;
the one image normaliser is the release's formula."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from deltar.contract import HYPOTHESIS_SAMPLINGS, SIZE_DIVISOR, normalise_image


def test_the_size_divisor_is_the_encoders_coarsest_stride():
    from deltar.models.encoders import FEATURE_STRIDES

    assert max(FEATURE_STRIDES) == SIZE_DIVISOR


@pytest.mark.parametrize("method", HYPOTHESIS_SAMPLINGS)
def test_every_sampling_name_samples(method):
    from deltar.sensor.sampling import sample_hypotheses

    mean, sigma = torch.tensor([1.0, 2.0]), torch.tensor([0.1, 0.2])
    out = sample_hypotheses(mean, sigma, torch.tensor([True, False]), 8, method)
    assert out.shape == (2, 8) and torch.all(out[1] == 0) and torch.all(out[0] > 0)


def test_an_unknown_sampling_name_is_refused():
    from deltar.sensor.sampling import sample_hypotheses

    with pytest.raises(ValueError, match="icdf"):
        sample_hypotheses(torch.ones(1), torch.ones(1), torch.ones(1, dtype=torch.bool), 4,
                          "normal")


def test_normalisation_is_the_release_formula(parity_fixture):
    """Bit for bit the release's float32 formula, on a uint8 image and on the same image
    in [0, 1] (as training hands it over after augmentation)."""
    image = parity_fixture["cases"][0]["image_rgb_uint8"]
    mean = torch.tensor([0.485, 0.456, 0.406]).view(1, 3, 1, 1)
    std = torch.tensor([0.229, 0.224, 0.225]).view(1, 3, 1, 1)
    expected = (image.permute(2, 0, 1)[None].float() / 255.0 - mean) / std
    assert torch.equal(torch.from_numpy(normalise_image(image.numpy()))[None], expected)
    as_float = image.numpy().astype(np.float32) / np.float32(255.0)
    assert torch.equal(torch.from_numpy(normalise_image(as_float))[None], expected)


def test_the_preset_names_are_the_models_presets():
    from deltar.contract import PRESET_NAMES
    from deltar.models import list_presets

    assert list(PRESET_NAMES) == list_presets()
