"""Which extra installs which optional module (deltar.extras)."""

from __future__ import annotations

import pytest

from deltar import extras


def test_messages_name_the_extra_that_installs_the_module():
    assert extras.missing_extra_message("timm.layers") == (
        "this command needs timm, which the 'torch' extra installs: pip install \"deltar[torch]\"")
    assert extras.missing_extra_message("lightning", "deltar train") == (
        "deltar train needs lightning, which the 'train' extra installs: "
        "pip install \"deltar[train]\"")
    assert extras.missing_extra_message("torch", "deltar export", "export").endswith(
        'pip install "deltar[export]"')
    assert extras.missing_extra_message("no_such_module") is None


def test_require_extra_raises_only_for_a_missing_module(monkeypatch):
    assert extras.module_available("numpy") and not extras.module_available("no_such_mod")
    extras.require_extra("onnx", "x") if extras.module_available("onnx") else None
    monkeypatch.setitem(extras.EXTRA_OF_MODULE, "no_such_mod", "plots")
    with pytest.raises(ModuleNotFoundError, match=r'deltar\[plots\]') as info:
        extras.require_extra("no_such_mod", "the plot")
    assert info.value.name == "no_such_mod"


def test_lazy_attributes_imports_on_first_use_and_names_unknown_ones():
    from deltar.camera import CameraIntrinsics
    from deltar.extras import lazy_attributes

    getter = lazy_attributes("deltar.example", {"CameraIntrinsics": "deltar.camera"})
    assert getter("CameraIntrinsics") is CameraIntrinsics
    with pytest.raises(AttributeError, match=r"module 'deltar\.example' has no attribute"):
        getter("nope")
