"""Pixel weights from the predicted sigma, and how the map uses them."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.mapping.frames import DepthSource, FrameSource, confidence_weight
from deltar.mapping.tsdf import MapSettings, TSDFMap
from tests.mapping.conftest import SMALL, WALL_Z_M, pose_at, render_wall

COARSE = MapSettings(voxel_size_m=0.04, truncation_voxels=3, max_depth_m=4.0)


def test_weight_is_the_inverse_variance_in_truncation_units():
    depth = np.full((2, 3), 2.0, np.float32)
    sigma = np.array([[0.0, 0.08, 0.16], [0.24, 0.31, 0.29]], np.float32)
    weight = confidence_weight(depth, sigma, truncation_m=0.08, max_relative_sigma=0.15)
    # 1 / (1 + (sigma / t)^2): 1, 1/2, 1/5, 1/10; 0.31 / 2 m is above 0.15 (skipped),
    # 0.29 / 2 m is not.
    assert weight[0] == pytest.approx([1.0, 0.5, 0.2], abs=1e-6)
    assert weight[1, 0] == pytest.approx(0.1, abs=1e-6)
    assert weight[1, 1] == 0.0
    assert weight[1, 2] == pytest.approx(1 / (1 + (0.29 / 0.08) ** 2), rel=1e-5)
    assert weight.dtype == np.float32


def test_weight_skips_pixels_without_depth_or_sigma():
    depth = np.array([[0.0, 1.0, np.nan, 1.0]], np.float32)
    sigma = np.array([[0.01, np.nan, 0.01, np.inf]], np.float32)
    weight = confidence_weight(depth, sigma, truncation_m=0.08, max_relative_sigma=0.5)
    assert np.all(weight == 0.0)


def test_weight_refuses_bad_arguments():
    depth = np.ones((2, 2), np.float32)
    with pytest.raises(ValueError, match="truncation_m"):
        confidence_weight(depth, depth, truncation_m=0.0, max_relative_sigma=0.15)
    with pytest.raises(ValueError, match="max_relative_sigma"):
        confidence_weight(depth, depth, truncation_m=0.08, max_relative_sigma=float("nan"))
    with pytest.raises(ValueError, match="uncertainty_m"):
        confidence_weight(depth, depth[:1], truncation_m=0.08, max_relative_sigma=0.15)
    with pytest.raises(ValueError, match="truncation_m"):
        DepthSource(method="nearest", truncation_m=-1.0)


def test_one_unsure_view_alone_still_makes_a_surface():
    # A pixel that nothing else observes is surface whatever its weight: the weight only
    # sets its share where views overlap.
    pose = pose_at(0.0)
    image, depth = render_wall(pose)
    volume = TSDFMap(COARSE)
    volume.integrate(depth, image, np.full_like(depth, 0.05), SMALL, pose)
    vertices = np.asarray(volume.mesh().vertices)
    assert len(vertices) > 100
    assert np.abs(vertices[:, 2] - WALL_Z_M).max() < 0.01
    # Asking for two observations per voxel leaves the single view out.
    assert len(volume.mesh(min_observations=2).vertices) == 0
    assert len(volume.points(min_observations=2)[0]) == 0
    with pytest.raises(ValueError, match="min_observations"):
        volume.points(min_observations=0)


def test_a_certain_view_outvotes_an_unsure_one_where_both_look():
    pose = pose_at(0.0)
    image, depth = render_wall(pose)
    truncation = COARSE.truncation_m
    sure = confidence_weight(depth, np.full_like(depth, 0.01), truncation_m=truncation,
                             max_relative_sigma=0.15)
    unsure = confidence_weight(depth, np.full_like(depth, 0.25), truncation_m=truncation,
                               max_relative_sigma=0.15)
    volume = TSDFMap(COARSE)
    volume.integrate(depth, image, sure, SMALL, pose)
    volume.integrate(depth + 0.06, image, unsure, SMALL, pose)  # 6 cm off
    z = np.median(np.asarray(volume.mesh().vertices)[:, 2])
    # Weights ~0.99 and ~0.13: the surface moves ~0.7 cm, not the 3 cm of a plain mean.
    share = unsure.flat[0] / (sure.flat[0] + unsure.flat[0])
    assert z == pytest.approx(WALL_Z_M + 0.06 * share, abs=0.004)
    assert z < WALL_Z_M + 0.015


def test_the_map_refuses_weights_made_for_another_truncation():
    from deltar.mapping.builder import build_map

    source = DepthSource(estimator=object(), truncation_m=0.05)
    with pytest.raises(ValueError, match=r"truncation of 0\.05 m, the map's is 0\.08 m"):
        build_map(None, source, None, MapSettings())


def test_the_models_pixels_beyond_the_zone_grid_are_left_out_unless_asked():
    from types import SimpleNamespace

    depth = np.full((40, 60), 2.0, dtype=np.float32)
    sigma = np.full_like(depth, 0.05)
    # Two zones spanning rows 10-30 and columns 15-45 (y0, x0, y1, x1): the grid's box.
    rects = np.array([[10, 15, 30, 30], [10, 30, 30, 45]], dtype=np.float32)

    class Estimator:
        weights = "fake"

        def predict(self, image, zone_frame, calibration):
            return SimpleNamespace(depth_m=depth, uncertainty_m=sigma, zone_rects=rects)

    frame = SimpleNamespace(image=np.zeros((40, 60, 3), np.uint8), zone_frame=None,
                            calibration=None, name="f")
    expected = confidence_weight(depth, sigma, truncation_m=0.08, max_relative_sigma=0.15)
    _, weight = DepthSource(Estimator(), truncation_m=0.08)(frame)
    inside = np.zeros(depth.shape, dtype=bool)
    inside[10:30, 15:45] = True
    np.testing.assert_array_equal(weight[inside], expected[inside])
    assert expected[~inside].min() > 0 and not weight[~inside].any()
    _, weight = DepthSource(Estimator(), truncation_m=0.08, beyond_grid=True)(frame)
    np.testing.assert_array_equal(weight, expected)


def _timed_recording(folder, image_times, zone_times):
    """The wall seen from one pose, with images and zone frames at the given times."""
    from deltar.io.recording import RecordingMeta, RecordingWriter
    from deltar.sensor.geometry import zone_rects
    from deltar.sensor.simulate_frame import simulate_zone_frame
    from deltar.sensor.zone_frame import ZoneFrame

    image, depth = render_wall(pose_at(0.0))
    zones = simulate_zone_frame(depth, zone_rects(SMALL, 8))
    writer = RecordingWriter(folder, RecordingMeta(SMALL))
    for t in image_times:
        writer.add_color(t, image)
    for t in zone_times:
        writer.add_zone_frame(ZoneFrame(zones.mean_m, zones.sigma_m, zones.valid,
                                        timestamp_s=t, no_target=zones.no_target))
    writer.close()
    return folder


def test_zone_frames_are_paired_with_the_calibrations_time_offset(tmp_path):
    from deltar.calibration.rig import RigCalibration
    from deltar.sensor.geometry import SensorExtrinsics

    # The camera's clock runs 0.5 s ahead of the sensor's.
    rec = _timed_recording(tmp_path / "rec", [1.0, 1.1, 1.2], [0.5, 0.6, 0.7])
    calib = RigCalibration(intrinsics=SMALL, extrinsics=SensorExtrinsics(), grid=8,
                           time_offset_s=0.5)
    source = FrameSource(rec, calibration=calib)
    assert [f.time_s for f in source.frames] == pytest.approx([1.0, 1.1, 1.2])


def test_one_zone_frame_per_image_and_unpaired_zone_frames_are_warned_of(tmp_path):
    # A sensor faster than the camera: 0.001 and 0.012 both find image 0.0 nearest; 0.5
    # has no image near it.
    rec = _timed_recording(tmp_path / "rec", [0.0, 0.1], [0.001, 0.012, 0.1, 0.5])
    with pytest.warns(UserWarning) as caught:
        source = FrameSource(rec)
    messages = " | ".join(str(w.message) for w in caught)
    assert "skipped 1 of 4 zone frames with no colour image" in messages
    assert "1 of 3 zone frames share a colour image" in messages
    assert [f.name for f in source.frames] == ["0", "100000000"]
    assert [f.zone_frame.timestamp_s for f in source.frames] == pytest.approx([0.001, 0.1])


def test_a_baseline_frame_without_a_valid_zone_fuses_nothing_and_is_counted(wall_recording):
    import dataclasses

    from deltar.mapping.builder import build_map, plan_map

    source = FrameSource(wall_recording)
    for frame in source.frames[:2]:
        zones = frame.zone_frame
        frame.zone_frame = dataclasses.replace(zones, valid=np.zeros_like(zones.valid),
                                               mean_m=np.zeros_like(zones.mean_m),
                                               sigma_m=np.zeros_like(zones.sigma_m))
    depth = DepthSource(method="nearest")
    for frame in source.load(source.frames[:1]):
        assert not depth(frame)[0].any()  # not the baseline's 2 m fallback
    plan = plan_map(source, COARSE)
    result = build_map(source, depth, plan, COARSE)
    assert result.empty_frames == 2 and len(result.poses) == 6


def test_a_bags_tof_frames_are_paired_with_the_calibrations_time_offset(tmp_path):
    from deltar.calibration.rig import RigCalibration
    from deltar.sensor.geometry import SensorExtrinsics
    from tests.capture.test_bag_replay import INTR, MS, _bag

    # The sensor's clock runs 300 ms behind the camera's, as `deltar replay --bag` pairs.
    _bag(tmp_path / "bag", [-296 * MS, -196 * MS, -96 * MS])
    calib = RigCalibration(INTR, SensorExtrinsics(), grid=8, time_offset_s=0.3)
    source = FrameSource(tmp_path / "bag", calibration=calib)
    assert [f.time_s for f in source.frames] == pytest.approx([0.0, 0.1, 0.2])
