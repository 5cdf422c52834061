"""The rerun viewer: ``--rerun-save`` recordings read back with rerun's own RRD reader."""

from __future__ import annotations

import numpy as np
import pyarrow as pa
import pytest
from rerun.chunk import RrdReader
from typer.testing import CliRunner

import deltar.cli.commands  # noqa: F401  (registers the commands)
from deltar.calibration.rig import RigCalibration
from deltar.camera import CameraIntrinsics
from deltar.capture.viewer import RerunLogger, zone_points_m
from deltar.cli.main import app
from deltar.inference.estimator import DepthEstimator
from deltar.sensor.geometry import SensorExtrinsics
from deltar.sensor.zone_frame import ZoneFrame
from tests.inference.fakes import ZonePainterNet

runner = CliRunner(env={"COLUMNS": "200"})
INTR = CameraIntrinsics(52.0, 52.0, 31.5, 23.5, 64, 48)


def read_rrd(path) -> dict[str, list[dict]]:
    """entity path -> rows (dicts of column -> value), in log order; times as int ns."""
    rows: dict[str, list[dict]] = {}
    for chunk in RrdReader(path).stream():
        batch = chunk.to_record_batch()
        columns = {name: (column.cast(pa.int64()) if pa.types.is_temporal(column.type)
                          else column)
                   for name, column in zip(batch.schema.names, batch.columns, strict=True)}
        rows.setdefault(chunk.entity_path, []).extend(pa.table(columns).to_pylist())
    return rows


def _buffer(row: dict, archetype: str) -> np.ndarray:
    fmt = row[f"{archetype}:format"][0]
    data = np.frombuffer(bytes(row[f"{archetype}:buffer"][0]), dtype=np.float32)
    return data.reshape(fmt["height"], fmt["width"])


def _frame(seed: int = 0) -> ZoneFrame:
    rng = np.random.default_rng(seed)
    valid = rng.random((8, 8)) > 0.15
    return ZoneFrame(mean_m=np.where(valid, rng.uniform(0.5, 3.0, (8, 8)), 0.0),
                     sigma_m=np.where(valid, 0.03, 0.0), valid=valid, timestamp_s=1.25)


def test_prediction_is_logged_as_pinhole_depth_zones_and_points(tmp_path):
    estimator = DepthEstimator(ZonePainterNet(), weights="painter")
    image = np.random.default_rng(1).integers(0, 256, (48, 64, 3), dtype=np.uint8)
    frame = _frame()
    extrinsics = SensorExtrinsics(translation_m=np.array([0.02, 0.0, 0.0]))
    calib = RigCalibration(INTR, extrinsics)
    prediction = estimator.predict(image, frame, calib)
    path = tmp_path / "view.rrd"
    with RerunLogger(path) as logger:
        logger.log_prediction(image, prediction, calibration=calib)
    rows = read_rrd(path)
    assert {"/world/camera/image", "/world/camera/image/depth", "/world/camera/image/zones",
            "/world/camera/tof", "/world/camera/tof/zones", "/uncertainty"} <= set(rows)
    # 3D points must not sit under the pinhole (rerun cannot draw them there).
    pinholes = [e for e, r in rows.items() if any("Pinhole:image_from_camera" in x for x in r)]
    assert pinholes == ["/world/camera/image"]
    pinhole = next(r for r in rows["/world/camera/image"] if "Pinhole:image_from_camera" in r)
    # rerun stores the 3x3 matrix column-major.
    np.testing.assert_allclose(np.reshape(pinhole["Pinhole:image_from_camera"][0], (3, 3)).T,
                               INTR.matrix, rtol=1e-6)
    (depth_row,) = rows["/world/camera/image/depth"]
    assert depth_row["DepthImage:meter"] == [1.0]
    np.testing.assert_allclose(_buffer(depth_row, "DepthImage"), prediction.depth_m)
    (unc_row,) = rows["/uncertainty"]
    np.testing.assert_allclose(_buffer(unc_row, "DepthImage"), prediction.uncertainty_m)
    (boxes,) = rows["/world/camera/image/zones"]
    labels = boxes["Boxes2D:labels"]
    mean, _, valid = frame.flat()
    assert len(labels) == 64
    assert labels[0] == (f"{mean[0]:.2f} m" if valid[0] else "-")
    assert sum(label == "-" for label in labels) == int((~valid).sum())
    # Box centres are the zone rectangles' centres in rerun's pixel-corner coordinates.
    rects = prediction.zone_rects
    centres = np.stack([(rects[:, 1] + rects[:, 3]) / 2 + 0.5,
                        (rects[:, 0] + rects[:, 2]) / 2 + 0.5], axis=1)
    np.testing.assert_allclose(np.array(boxes["Boxes2D:centers"]), centres, rtol=1e-5)
    (pose,) = rows["/world/camera/tof"]
    np.testing.assert_allclose(pose["Transform3D:translation"][0], [0.02, 0.0, 0.0])
    (points,) = rows["/world/camera/tof/zones"]
    positions = np.array(points["Points3D:positions"])
    assert positions.shape == (int(valid.sum()), 3)
    np.testing.assert_allclose(positions[:, 2], mean[valid], rtol=1e-6)


def test_zone_points_lie_on_their_zone_rays():
    frame = _frame(2)
    points, index = zone_points_m(frame, (45.0, 45.0))
    valid = frame.flat()[2]
    np.testing.assert_array_equal(index, np.flatnonzero(valid))
    # The 8x8 grid over 45 degrees: zone (r, c) has its centre at (c - 3.5) * 5.625 deg.
    rows, cols = np.divmod(index, 8)
    np.testing.assert_allclose(points[:, 0] / points[:, 2],
                               np.tan(np.deg2rad((cols - 3.5) * 45 / 8)), rtol=1e-5)
    np.testing.assert_allclose(points[:, 1] / points[:, 2],
                               np.tan(np.deg2rad((rows - 3.5) * 45 / 8)), rtol=1e-5)


def test_existing_recording_is_not_overwritten(tmp_path):
    path = tmp_path / "x.rrd"
    path.write_bytes(b"keep")
    with pytest.raises(FileExistsError):
        RerunLogger(path)
    assert path.read_bytes() == b"keep"


def test_missing_rerun_names_the_extra(tmp_path, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "rerun", None)
    with pytest.raises(ImportError, match=r'pip install "deltar\[viewer\]"'):
        RerunLogger(tmp_path / "x.rrd")
    result = runner.invoke(app, ["record", str(tmp_path / "rec"), "--simulate", "wall:1:2",
                                 "--rerun-save", str(tmp_path / "x.rrd")])
    assert result.exit_code == 1 and 'needs the "viewer" extra' in result.output
    assert not (tmp_path / "rec").exists()  # nothing recorded when the viewer is missing
