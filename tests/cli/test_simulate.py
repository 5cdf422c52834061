"""``deltar simulate``: writes a readable ZJU-L5 set and never writes into existing data."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image
from typer.testing import CliRunner

from deltar.cli.main import app
from deltar.data.procedural import render_scene
from deltar.data.zju_l5 import ZJUL5Dataset
from deltar.sensor.geometry import zone_rects_to_pixel_bounds

runner = CliRunner()


def test_procedural_source_round_trip(tmp_path):
    out = tmp_path / "set"
    result = runner.invoke(app, ["simulate", "procedural:3:4:48x64", str(out), "--grid", "4",
                                 "--start", "1"])
    assert result.exit_code == 0, result.output
    ds = ZJUL5Dataset(out / "data.json")
    assert [s.name for s in ds] == ["procedural/procedural-5", "procedural/procedural-6"]
    sample = ds[0]
    frame = render_scene(5, 48, 64)
    np.testing.assert_array_equal(sample.depth_m, frame.depth_m)
    np.testing.assert_array_equal(sample.rgb, frame.image)
    assert sample.intrinsics == frame.intrinsics
    assert sample.zone_valid.shape == (16,) and sample.zone_valid.any()
    # Each valid zone's mean lies within the depth range of the pixels the zone covers.
    bounds = zone_rects_to_pixel_bounds(sample.zone_rects, 48, 64)
    for (y0, x0, y1, x1), (mean, _), ok in zip(bounds, sample.zone_mean_sigma,
                                               sample.zone_valid, strict=True):
        if ok:
            patch = frame.depth_m[y0:y1, x0:x1]
            assert patch.min() - 0.04 <= mean <= patch.max() + 0.04


def test_folder_source_with_frame_range(shared_data, tmp_path):
    out = tmp_path / "kitchen"
    result = runner.invoke(app, ["simulate", str(shared_data / "7scenes_redkitchen"), str(out),
                                 "--start", "10", "--stop", "20", "--step", "5", "--limit", "1",
                                 "--layout", "aligned"])
    assert result.exit_code == 0, result.output
    (sample,) = list(ZJUL5Dataset(out))
    assert sample.name == "7scenes_redkitchen/frame-000020"  # frame 10 of every-2nd frames
    # The release's aligned layout: 56 px zones from (16, 96) at 480x640.
    np.testing.assert_array_equal(sample.zone_rects[0], [16, 96, 72, 152])
    np.testing.assert_array_equal(sample.zone_rects[63], [408, 488, 464, 544])


def test_zones_that_see_past_the_range_are_written_as_no_target(shared_data, tmp_path):
    # The office's window side lies beyond the L5's 4 m: those zones report no target,
    # in the clean set and, unchanged, in a degraded one (dropping acts on readings).
    sets = {}
    for name, extra in (("clean", []), ("degraded", ["--drop-fraction", "0.5"]),
                        ("noflags", ["--without-no-target-flags"])):
        result = runner.invoke(app, ["simulate", str(shared_data / "realsense_office"),
                                     str(tmp_path / name), "--limit", "1",
                                     "--intrinsics", "615,615,320,240", *extra])
        assert result.exit_code == 0, result.output
        (sets[name],) = list(ZJUL5Dataset(tmp_path / name))
    sample = sets["clean"]
    flags = sample.zone_no_target
    assert flags.any() and not (flags & sample.zone_valid).any()
    for zone in np.flatnonzero(flags):
        y0, x0, y1, x1 = np.ceil(sample.zone_rects[zone]).astype(int).clip(0)
        depth = sample.depth_m[y0:y1, x0:x1]
        assert (depth > 4.0).sum() > ((depth > 0) & (depth <= 4.0)).sum()
    np.testing.assert_array_equal(sets["degraded"].zone_no_target, flags)
    assert sets["degraded"].zone_valid.sum() < sample.zone_valid.sum()
    # As the released ZJU-L5 files store them: the same readings, no flags.
    assert sets["noflags"].zone_no_target is None
    np.testing.assert_array_equal(sets["noflags"].zone_valid, sample.zone_valid)
    np.testing.assert_array_equal(sets["noflags"].zone_mean_sigma, sample.zone_mean_sigma)


def test_refuses_non_empty_output_and_bad_options(tmp_path):
    out = tmp_path / "busy"
    out.mkdir()
    (out / "keep.txt").write_text("user data")
    result = runner.invoke(app, ["simulate", "procedural:1:0:16x16", str(out)])
    assert result.exit_code != 0
    assert "refusing" in result.output
    assert (out / "keep.txt").read_text() == "user data"
    result = runner.invoke(app, ["simulate", "procedural:1", str(tmp_path / "x"), "--grid", "5"])
    assert result.exit_code != 0
    # An empty split name wrote data.json as {"": [...]}.
    result = runner.invoke(app, ["simulate", "procedural:1:0:32x32", str(tmp_path / "y"),
                                 "--split", " "])
    assert result.exit_code == 2 and "--split" in result.output
    assert "non-empty name" in result.output and not (tmp_path / "y").exists()


@pytest.mark.parametrize("option", [["--stop", "-3"], ["--start", "-1"], ["--step", "0"],
                                    ["--limit", "0"]])
def test_a_negative_frame_range_is_refused_not_read_as_a_slice(tmp_path, option):
    # "--stop -3" would otherwise select all but the last three frames.
    result = runner.invoke(app, ["simulate", "procedural:4:0:32x32", str(tmp_path / "o"),
                                 *option])
    assert result.exit_code == 2, result.output
    assert "--start and --stop must be >= 0, --step and --limit >= 1" in result.output
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("spec", ["procedural:x", "procedural:2:1:48by64", "procedural:2:-5",
                                  "procedural:2:0:64x96:7"])
def test_bad_procedural_spec(tmp_path, spec):
    result = runner.invoke(app, ["simulate", spec, str(tmp_path / "o")])
    assert result.exit_code == 2  # a usage error with a message, not a traceback
    assert "procedural source must look like" in result.output


def test_intrinsics_option_overrides_the_source(tmp_path):
    rng = np.random.default_rng(0)
    src = tmp_path / "src"
    (src / "color").mkdir(parents=True)
    (src / "depth").mkdir()
    Image.fromarray(rng.integers(0, 256, (32, 48, 3), dtype=np.uint8)).save(
        src / "color" / "0001.png")
    Image.fromarray(np.full((32, 48), 1500, np.uint16)).save(src / "depth" / "0001.png")
    out = tmp_path / "k"
    result = runner.invoke(app, ["simulate", str(src), str(out), "--grid", "4",
                                 "--intrinsics", "30,31,20.5,15.5"])
    assert result.exit_code == 0, result.output
    sample = ZJUL5Dataset(out)[0]
    assert sample.name == "src/0001"
    assert (sample.intrinsics.fx, sample.intrinsics.fy, sample.intrinsics.cx,
            sample.intrinsics.cy) == (30.0, 31.0, 20.5, 15.5)
    # The calibrated grid spans 2 * fx * tan(22.5 deg) pixels across.
    span = sample.zone_rects[:, 3].max() - sample.zone_rects[:, 1].min()
    assert span == pytest.approx(2 * 30.0 * np.tan(np.deg2rad(22.5)), rel=1e-5)
    np.testing.assert_allclose(sample.zone_mean_sigma[sample.zone_valid, 0], 1.5)
    for bad in (["--intrinsics", "30,31"],
                ["--intrinsics", "30,31,20.5,15.5", "--depth-scale", "0"]):
        result = runner.invoke(app, ["simulate", str(src), str(tmp_path / "bad"), *bad])
        assert result.exit_code == 2, bad
    result = runner.invoke(app, ["simulate", "procedural:1", str(tmp_path / "p"),
                                 "--intrinsics", "30,31,20.5,15.5"])
    assert result.exit_code == 2 and "own camera" in result.output


def test_cnh_histograms_are_written_with_their_bins(tmp_path):
    from deltar.sensor.cnh import CNHConfig, simulate_cnh

    out = tmp_path / "cnh"
    result = runner.invoke(app, ["simulate", "procedural:1:7:48x64", str(out), "--cnh-bins",
                                 "12", "--cnh-range", "0.5:5.0"])
    assert result.exit_code == 0, result.output
    assert "12 bins" in result.output
    (sample,) = list(ZJUL5Dataset(out))
    config = CNHConfig.from_range(0.5, 5.0, 12)
    np.testing.assert_allclose(sample.hist_edges_m, config.edges_m(), rtol=1e-6)
    assert sample.hist_counts.shape == (64, 12)
    frame = render_scene(7, 48, 64)
    np.testing.assert_allclose(sample.hist_counts,
                               simulate_cnh(frame.depth_m, sample.zone_rects, config), atol=1e-7)
    # Every zone whose pixels lie in range has a histogram summing to 1, peaking where
    # most of its pixels are.
    bounds = zone_rects_to_pixel_bounds(sample.zone_rects, 48, 64)
    y0, x0, y1, x1 = bounds[27]
    patch = frame.depth_m[y0:y1, x0:x1]
    assert sample.hist_counts[27].sum() == pytest.approx(1.0, abs=1e-6)
    peak = sample.hist_counts[27].argmax()
    share = np.mean((patch >= sample.hist_edges_m[peak]) & (patch < sample.hist_edges_m[peak + 1]))
    assert share == pytest.approx(sample.hist_counts[27, peak], abs=1e-6)
    default = runner.invoke(app, ["simulate", "procedural:1:7:48x64", str(tmp_path / "d"),
                                  "--cnh"])
    assert default.exit_code == 0 and "18 bins" in default.output
    bad = runner.invoke(app, ["simulate", "procedural:1", str(tmp_path / "e"),
                              "--cnh-range", "4:1"])
    assert bad.exit_code != 0 and "near < far" in bad.output


def test_degraded_signal_drops_and_biases_zones_reproducibly(tmp_path):
    args = ["simulate", "procedural:2:4:48x64", "--grid", "8"]
    clean, a, b = tmp_path / "clean", tmp_path / "a", tmp_path / "b"
    degrade = ["--drop-fraction", "0.5", "--bias-prob", "1.0", "--bias-mean", "-0.3",
               "--bias-std", "0.0", "--seed", "3"]
    for out, extra in ((clean, []), (a, degrade), (b, degrade)):
        result = runner.invoke(app, [*args[:2], str(out), *args[2:], *extra])
        assert result.exit_code == 0, result.output
    for s_clean, s_a, s_b in zip(ZJUL5Dataset(clean / "data.json"), ZJUL5Dataset(a / "data.json"),
                                 ZJUL5Dataset(b / "data.json"), strict=True):
        assert np.array_equal(s_a.zone_valid, s_b.zone_valid)  # same seed, same draws
        kept = s_a.zone_valid
        assert kept.sum() == s_clean.zone_valid.sum() - int(0.5 * s_clean.zone_valid.sum())
        assert not (kept & ~s_clean.zone_valid).any()
        # Every remaining zone is biased by exactly -0.3 m.
        np.testing.assert_allclose(s_a.zone_mean_sigma[kept, 0],
                                   s_clean.zone_mean_sigma[kept, 0] - 0.3, atol=1e-5)


def test_readings_biased_past_the_sensor_range_are_not_reported(tmp_path):
    out = tmp_path / "far"
    result = runner.invoke(app, ["simulate", "procedural:1:4:48x64", str(out), "--grid", "4",
                                 "--bias-prob", "1.0", "--bias-mean", "5.0", "--bias-std",
                                 "0.0"])
    assert result.exit_code == 0, result.output
    sample = ZJUL5Dataset(out / "data.json")[0]
    assert not sample.zone_valid.any()  # every reading was pushed beyond 4 m
    assert (sample.zone_mean_sigma == 0).all()


def test_several_targets_per_zone_are_written_and_read_back(tmp_path):
    out, single = tmp_path / "targets", tmp_path / "single"
    for folder, extra in ((out, ["--targets", "4"]), (single, [])):
        result = runner.invoke(app, ["simulate", "procedural:2:4:96x128", str(folder),
                                     "--grid", "8", *extra])
        assert result.exit_code == 0, result.output
    seconds = 0
    for sample, plain in zip(ZJUL5Dataset(out / "data.json"),
                             ZJUL5Dataset(single / "data.json"), strict=True):
        assert plain.target_mean_m is None  # one target: the files are as before
        np.testing.assert_array_equal(sample.zone_mean_sigma, plain.zone_mean_sigma)
        assert sample.target_mean_m.shape == (64, 4)
        np.testing.assert_array_equal(sample.target_valid[:, 0], sample.zone_valid)
        np.testing.assert_allclose(sample.target_mean_m[sample.zone_valid, 0],
                                   sample.zone_mean_sigma[sample.zone_valid, 0])
        frame = sample.zone_frame()
        assert frame.targets_per_zone == 4 and frame.target_signal is not None
        second = sample.target_valid[:, 1]
        seconds += int(second.sum())
        # The sensor separates targets at least 0.6 m apart.
        gap = np.abs(sample.target_mean_m[second, 1] - sample.target_mean_m[second, 0])
        assert np.all(gap >= 0.6 - 0.04)
    assert seconds > 0  # procedural rooms have depth edges inside zones
    result = runner.invoke(app, ["simulate", "procedural:1:4:48x64", str(tmp_path / "bad"),
                                 "--targets", "5"])
    assert result.exit_code != 0 and "--targets" in result.output


def test_degraded_targets_follow_their_zone(tmp_path):
    out, clean = tmp_path / "degraded", tmp_path / "clean"
    args = ["procedural:2:4:96x128", "--grid", "8", "--targets", "4"]
    degrade = ["--drop-fraction", "0.5", "--bias-prob", "1.0", "--bias-mean", "0.2",
               "--bias-std", "0.0", "--seed", "3"]
    for folder, extra in ((clean, []), (out, degrade)):
        result = runner.invoke(app, ["simulate", args[0], str(folder), *args[1:], *extra])
        assert result.exit_code == 0, result.output
    for s_deg, s_clean in zip(ZJUL5Dataset(out / "data.json"),
                              ZJUL5Dataset(clean / "data.json"), strict=True):
        zone_kept = s_deg.zone_valid
        assert not (s_deg.target_valid & ~zone_kept[:, None]).any()  # dropped: all lost
        assert s_deg.zone_frame().physical_error() is None  # target 0 the degraded primary
        both = s_clean.target_valid[:, 1] & zone_kept
        factor = s_deg.zone_mean_sigma[both, 0] / s_clean.zone_mean_sigma[both, 0]
        scaled = s_clean.target_mean_m[both, 1] * factor
        reported = s_deg.target_valid[both, 1]
        np.testing.assert_allclose(s_deg.target_mean_m[both, 1][reported], scaled[reported],
                                   rtol=1e-5)
        assert np.all(scaled[~reported] > 4.0)  # pushed past the range: not reported
