"""The network's per-part configs: checks naming the option, the stored round trip."""

from __future__ import annotations

import pytest

from deltar.contract import network_contract
from deltar.models import DeltarNet, create_model
from deltar.models.config import (
    FLAT_OPTIONS,
    DescriptorConfig,
    FusionConfig,
    HeadConfig,
    InputConfig,
    NetworkConfig,
    OutputConfig,
    PlaneSelectConfig,
)
from deltar.models.presets import PRESETS


def test_config_round_trips_through_the_network():
    model = create_model("deltar-select", design_size=(64, 96), planar=False)
    twin = DeltarNet.from_config(model.config())
    assert twin.config() == model.config()
    assert twin.network_config == model.network_config
    assert set(twin.state_dict()) == set(model.state_dict())
    assert model.config()["head"] == {"name": "plane_select", "n_bins": 64,
                                      "temperature": 5.0, "planar": False}


@pytest.mark.parametrize("make, match", [
    (lambda: NetworkConfig.from_dict({"head": {"n_bin": 3}}), r"unknown head options.*n_bin"),
    (lambda: NetworkConfig.from_dict({"neck": {}}), r"unknown network config sections"),
    (lambda: NetworkConfig().with_options(n_bin=3), r"unknown network options.*n_bin"),
    (lambda: HeadConfig(name="magic"), "head must be one of"),
    (lambda: HeadConfig(name="plane_select"), "takes a PlaneSelectConfig"),
    (lambda: FusionConfig(name="unet"), "decoder must be one of"),
    (lambda: FusionConfig(channels=(8, 8)), "decoder_channels"),
    (lambda: DescriptorConfig(strides=(6,)), "descriptor strides"),
    (lambda: NetworkConfig(head=OutputConfig()), "the head part must be one of"),
    (lambda: NetworkConfig.from_dict({"decoder": {"name": "descriptors", "channels": [8]}}),
     r"unknown decoder options \['channels'\] for DescriptorConfig"),
    (lambda: PRESETS["deltar-lite"].with_options(planar=False),
     r"head 'zone_prior' has no option \['planar'\]"),
    (lambda: InputConfig(design_size=(65, 96)), "design_size"),
    # Divisible by 32 too: a traceback at the first forward pass (train, export) before.
    (lambda: InputConfig(design_size=(0, 0)), "design_size"),
    (lambda: InputConfig(design_size=(-32, 64)), "design_size"),
    (lambda: InputConfig(image_std=(0.5, 0.0, 0.5)), "image_std"),
    (lambda: OutputConfig(min_depth=2.0, max_depth=1.0), "min_depth"),
    (lambda: OutputConfig(max_depth=4.0), "no_target_depth"),
    (lambda: NetworkConfig(decoder=DescriptorConfig()), "decoder 'descriptors'"),
])
def test_bad_values_name_the_option(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_flat_options_cover_every_field_once_and_read_back():
    targets = list(FLAT_OPTIONS.values())
    assert len(set(targets)) == len(targets)
    covered = set()
    for spec in PRESETS.values():
        covered |= {(s, f) for s, fields in spec.to_dict().items() for f in fields}
        assert NetworkConfig.from_flat(spec.flat_options()) == spec
    assert covered == set(targets)


def test_switching_the_head_keeps_the_shared_bin_count():
    lite = PRESETS["deltar-lite"]
    select = lite.with_options(decoder="descriptors", head="plane_select", planar=False)
    assert select.head == PlaneSelectConfig(n_bins=64, planar=False)
    assert select.decoder == DescriptorConfig()
    assert lite.with_options(head="bins").head == HeadConfig(name="bins", n_bins=64)
    # Format-2 files store every option of every kind: the others are dropped.
    stored = {**lite.flat_options(), "planar": True, "descriptor_strides": (8, 16)}
    assert PRESETS["deltar-official"].with_stored_options(stored) == lite


def test_contract_is_the_same_from_either_stored_form():
    spec = PRESETS["deltar-select"].with_options(design_size=(64, 96))
    sectioned, flat = network_contract(spec.to_dict()), network_contract(spec.flat_options())
    assert sectioned == flat
    assert sectioned["head"] == "plane_select" and sectioned["design_size"] == (64, 96)
    assert "backbone" not in sectioned
