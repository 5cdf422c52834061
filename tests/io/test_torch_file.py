"""read_torch_file: loads torch files; missing or corrupt files are named."""

from __future__ import annotations

import pytest
import torch

from deltar.io.torch_file import read_torch_file


def test_round_trip_and_errors_name_the_file(tmp_path):
    good = tmp_path / "good.pt"
    torch.save({"w": torch.arange(3)}, good)
    assert torch.equal(read_torch_file(good, "weights", weights_only=True)["w"],
                       torch.arange(3))
    with pytest.raises(FileNotFoundError, match=r"weights not found: .*missing\.pt"):
        read_torch_file(tmp_path / "missing.pt", "weights", weights_only=True)
    corrupt = tmp_path / "corrupt.pt"
    corrupt.write_bytes(b"not a torch file")
    with pytest.raises(ValueError, match=r"corrupt\.pt: cannot read weights"):
        read_torch_file(corrupt, "weights", weights_only=True)
    assert corrupt.read_bytes() == b"not a torch file"  # the input is left alone
