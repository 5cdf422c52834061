"""The wall test (hand-computed bias from the 4 cm simulator bins)."""

from __future__ import annotations

import json
import warnings

import pytest

from deltar.capture.drivers import SimulatedRig
from deltar.capture.record import record
from deltar.data.flat_wall import FlatWallSource
from deltar.data.procedural import ProceduralReader
from deltar.evaluation.wall_test import evaluate_recording, wall_test, write_results
from deltar.inference.estimator import DepthEstimator
from tests.inference.fakes import ZonePainterNet


def _recording(folder, distance):
    record(folder, SimulatedRig(FlatWallSource(distance, 4, 48, 64)))
    return folder


def test_wall_test_bias_is_the_bin_quantisation(tmp_path):
    """A wall at d reads as the centre of its 4 cm bin: bias = |centre - d|, jitter 0.

    Walls at 1.01 m and 2.05 m fall in the bins centred at 1.02 m and 2.06 m, so both
    the raw zones and the zone-painting network are 0.01 m off, with no spread.
    """
    estimator = DepthEstimator(ZonePainterNet(), weights="painter")
    recordings = [_recording(tmp_path / "far", 2.05), _recording(tmp_path / "near", 1.01)]
    with warnings.catch_warnings():
        warnings.filterwarnings("error", message=".*flat wall")  # walls: no warning
        results = wall_test(recordings, estimator)
    assert [r.distance_m for r in results] == pytest.approx([1.02, 2.06], abs=1e-5)
    for result in results:
        assert result.frames == 2 and result.reference == "depth"
        assert result.zones_bias_m == pytest.approx(0.01, abs=1e-5)
        assert result.zones_jitter_m == pytest.approx(0.0, abs=1e-5)
        assert result.network_bias_m == pytest.approx(0.01, abs=1e-4)
        assert result.network_jitter_m == pytest.approx(0.0, abs=1e-4)
    paths = write_results(tmp_path / "out", results, title="painter")
    data = json.loads(paths["json"].read_text())
    assert len(data["results"]) == 2 and paths["plot"].stat().st_size > 0
    assert paths["csv"].read_text().splitlines()[0].startswith("recording,distance_m")
    with pytest.raises(FileExistsError):
        write_results(tmp_path / "out", results)


def test_recording_without_reference_depth_fits_the_plane_to_itself(tmp_path):
    folder = _recording(tmp_path / "rec", 1.01)
    for path in (folder / "depth").iterdir():
        path.unlink()
    (folder / "depth").rmdir()
    estimator = DepthEstimator(ZonePainterNet(), weights="painter")
    result = evaluate_recording(folder, estimator)
    assert result.reference == "self"
    assert result.zones_bias_m == pytest.approx(0.0, abs=1e-5)  # flat, so no bias to itself


def test_wall_test_needs_recordings():
    with pytest.raises(ValueError, match="at least one"):
        wall_test([], DepthEstimator(ZonePainterNet(), weights="painter"))


def test_a_recording_that_is_not_a_flat_wall_is_warned_about_once(tmp_path):
    # Procedural rooms: several planes, few pixels on any one plane fit. Before, their
    # bias and jitter came out as a wall's, without a word.
    folder = tmp_path / "room"
    record(folder, SimulatedRig(ProceduralReader(4, 1, 96, 128)))
    estimator = DepthEstimator(ZonePainterNet(), weights="painter")
    with pytest.warns(UserWarning, match=r"room: the plane fitted to its reference depth "
                      r"keeps only \d+% of the pixels as inliers \(mean over \d frames; a "
                      r"flat wall keeps over 80%\): it does not look like one flat wall") as got:
        result = evaluate_recording(folder, estimator)
    assert result.reference == "depth"
    assert sum("flat wall" in str(w.message) for w in got) == 1
