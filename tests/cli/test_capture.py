"""``deltar record --targets``: several targets per zone, with their signals, recorded."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

import deltar.cli.commands  # noqa: F401  (registers the commands)
from deltar.cli.main import app
from deltar.io.recording import Recording
from deltar.io.rosbag_reader import BagInput

runner = CliRunner(env={"COLUMNS": "200"})
SOURCE = "procedural:4:4:96x128"


def _frames(out, bag: bool):
    if bag:
        return [pair.zone_frame for pair in BagInput(out).pairs()]
    return Recording(out).zone_frames()


@pytest.mark.parametrize("bag", [False, True], ids=["folder", "bag"])
def test_record_simulate_with_targets_keeps_every_target_and_its_signal(tmp_path, bag):
    out, single = tmp_path / "targets", tmp_path / "single"
    extra = ["--bag"] if bag else []
    for folder, targets in ((out, ["--targets", "3"]), (single, [])):
        result = runner.invoke(app, ["record", str(folder), "--simulate", SOURCE,
                                     "--sensor-hz", "30", *targets, *extra])
        assert result.exit_code == 0, result.output
    frames, plain = _frames(out, bag), _frames(single, bag)
    assert len(frames) == len(plain) > 0
    seconds = 0
    for frame, one in zip(frames, plain, strict=True):
        assert one.target_mean_m is None and one.target_signal is None
        assert frame.targets_per_zone == 3
        np.testing.assert_array_equal(frame.valid, one.valid)
        np.testing.assert_allclose(frame.mean_m, one.mean_m, atol=1e-6)
        valid = frame.target_valid
        assert np.all(frame.target_signal[valid] > 0)
        assert np.all(frame.target_signal[~valid] == 0)
        seconds += int(valid[..., 1].sum())
    assert seconds > 0  # these procedural rooms have depth edges inside a few zones


def test_record_targets_out_of_range_is_refused(tmp_path):
    result = runner.invoke(app, ["record", str(tmp_path / "rec"), "--simulate", "wall:1.5:2",
                                 "--targets", "5"])
    assert result.exit_code != 0 and "--targets" in result.output
    assert not (tmp_path / "rec").exists()
