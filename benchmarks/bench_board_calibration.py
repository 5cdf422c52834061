"""Accuracy of the board calibration (no depth camera) and of the depth-image path.

Synthetic rigs: a 640x480 camera (fx 500, fy 505), an 8x8 sensor rolled 91.5 deg, tilted
2 and -1.5 deg, 4.6 cm from the camera; a ChArUco 7x5 board (40 mm squares, A4) on a
wall seen from 0.5-0.9 m, tilted 25-45 deg (``--tilt 35,15``: the earlier 15-35); 2 cm
zone noise, 10 % invalid zones; the guess is roll 90 deg, translation 0. Run from the
repository root::

    PYTHONPATH=src python benchmarks/bench_board_calibration.py [--part board|intrinsics|
        refusal|depth|bound] [--seeds 5] [--first-seed 0] [--tilt 45,25] [--views 15,20,25]
        [--zone-noise 0.02] [--invalid 0.1] [--near 0]

``--near N`` draws N of the views 0.3-0.45 m from the board (it fills most of the
image), as the guide asks for ``--calibrate-intrinsics``; the other views are those of
the same seed without it.

``--zone-noise 0 --invalid 0`` measures what is left without the zones' noise (the bias of
the solver's model of the zone readings and the board poses' own error).

``--part bound`` prints the expected error (the Cramer-Rao bound of
:mod:`deltar.calibration.board_uncertainty`) of the view geometries, without rendering.

``--part depth`` is the box-room sweep of docs/calibration.md (depth images); run it
with another checkout's ``src`` first on PYTHONPATH to compare versions.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from deltar.calibration.extrinsic import depth_to_points, nominal_extrinsics
from deltar.camera import CameraIntrinsics
from deltar.sensor.geometry import SensorExtrinsics

CAMERA = CameraIntrinsics(500.0, 505.0, 322.0, 238.0, 640, 480)
ROUGH = CameraIntrinsics(540.0, 464.6, 330.0, 230.0, 640, 480)  # fx +8 %, fy -8 %
DISTORTION = (-0.12, 0.05, 0.001, -0.001)
TRUE = SensorExtrinsics(Rotation.from_euler("zyx", [91.5, 2.0, -1.5], degrees=True).as_matrix(),
                        np.array([0.04, -0.02, 0.01]))
NEAR_M = (0.3, 0.45)
TARGET = "charuco:7x5:0.04:0.03:DICT_5X5_100"


def errors(found: SensorExtrinsics, truth: SensorExtrinsics = TRUE) -> tuple[float, float]:
    """(rotation error in degrees, translation error in millimetres)."""
    angle = Rotation.from_matrix(found.rotation @ truth.rotation.T).magnitude()
    return float(np.degrees(angle)), 1000 * float(np.linalg.norm(found.translation_m -
                                                                 truth.translation_m))


def board_run(folder: Path, views: int, seed: int, *, intrinsics: bool = False,
              tilt: tuple[float, float] = (45.0, 25.0), zone_noise_m: float = 0.02,
              invalid_fraction: float = 0.1, near: int = 0):
    from deltar.calibration.board import parse_board_spec
    from deltar.calibration.board_pipeline import calibrate_recording_with_board
    from deltar.calibration.synthetic_board import board_view_poses, write_board_recording
    from deltar.io.recording import Recording

    spec = parse_board_spec(TARGET)
    poses = board_view_poses(views - near, distance_m=(0.5, 0.9), tilt_deg=tilt[0],
                             min_tilt_deg=tilt[1], seed=seed)
    # Views close enough for the board to fill most of the image (for the intrinsics).
    poses += board_view_poses(near, distance_m=NEAR_M, tilt_deg=tilt[0],
                              min_tilt_deg=tilt[1], seed=10_000 + seed)
    write_board_recording(folder, TRUE, CAMERA, spec, poses,
                          recorded_intrinsics=ROUGH if intrinsics else None,
                          distortion=DISTORTION if intrinsics else (),
                          mean_noise_m=zone_noise_m, invalid_fraction=invalid_fraction,
                          seed=seed)
    start = time.perf_counter()
    result, report = calibrate_recording_with_board(Recording(folder), spec,
                                                    nominal_extrinsics(90.0),
                                                    calibrate_intrinsics=intrinsics)
    return result, report, time.perf_counter() - start


def expected(report) -> str:
    """The report's expected errors (1 sd) and the chance of missing 0.5 deg or 10 mm."""
    u = report.uncertainty
    return (f"{u.rotation_rms_deg:.2f} / {1000 * u.translation_rms_m:.1f} / "
            f"{100 * u.miss_probability(0.5, 0.010):.0f} %")


def part_board(seeds: range, tilt: tuple[float, float], view_counts: tuple[int, ...],
               near: int = 0, **zones) -> None:
    print("| views | seed | rotation error (deg) | translation error (mm) | expected (deg / mm "
          "/ chance of a miss) | before -> after zone-to-cloud (cm) | solve (s) |")
    print("|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for views in view_counts:
            for seed in seeds:
                result, report, took = board_run(Path(tmp) / f"b{views}_{seed}", views, seed,
                                                 tilt=tilt, near=near, **zones)
                angle, shift = errors(result.calibration.extrinsics)
                print(f"| {views} | {seed} | {angle:.3f} | {shift:.1f} | {expected(report)} | "
                      f"{100 * result.distance_before_m:.2f} -> "
                      f"{100 * result.distance_after_m:.2f} | {took:.1f} |", flush=True)


def part_intrinsics(seeds: range, tilt: tuple[float, float], near: int = 0, **zones) -> None:
    print("| seed | fx error (%) | fy error (%) | cx, cy error (px) | cx, cy sd (px) | k1 | "
          "rotation error (deg) | translation error (mm) | expected (deg / mm / chance of a "
          "miss) | reprojection RMS (px) |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for seed in seeds:
            result, report, _ = board_run(Path(tmp) / f"i{seed}", 20, seed, intrinsics=True,
                                          tilt=tilt, near=near, **zones)
            k = result.calibration.intrinsics
            angle, shift = errors(result.calibration.extrinsics)
            print(f"| {seed} | {100 * (k.fx / CAMERA.fx - 1):+.2f} | "
                  f"{100 * (k.fy / CAMERA.fy - 1):+.2f} | {k.cx - CAMERA.cx:+.1f}, "
                  f"{k.cy - CAMERA.cy:+.1f} | {report.camera.sd[2]:.1f}, "
                  f"{report.camera.sd[3]:.1f} | {result.calibration.distortion[0]:+.3f} | "
                  f"{angle:.3f} | {shift:.1f} | {expected(report)} | "
                  f"{report.intrinsics_rms_px:.2f} |", flush=True)


def part_bound(seeds: range) -> None:
    """Expected errors of view geometries: true planes, simulated zones, 2 cm noise."""
    from deltar.calibration.board_uncertainty import extrinsic_uncertainty
    from deltar.calibration.synthetic import (
        sensor_pose,
        sensor_virtual_camera,
        simulated_zone_frame,
    )
    from deltar.calibration.synthetic_board import WALL, board_view_poses

    sensor_cam, rects = sensor_virtual_camera()
    print("| tilt (deg) | views | expected rotation error, mean over seeds (deg) | expected "
          "translation error (mm) | chance of missing 0.5 deg or 10 mm |")
    print("|---|---|---|---|---|")
    for tilt in ((35.0, 15.0), (40.0, 20.0), (45.0, 25.0)):
        for views in (15, 20, 25):
            rows = []
            for seed in seeds:
                rng = np.random.default_rng(seed)
                poses = board_view_poses(views, distance_m=(0.5, 0.9), tilt_deg=tilt[0],
                                         min_tilt_deg=tilt[1], seed=seed)
                planes, means, masks = [], [], []
                for pose in poses:
                    # The wall in the camera frame; its normal already faces the camera.
                    planes.append((pose[:3, :3].T @ WALL[0, :3],
                                   float(WALL[0, :3] @ pose[:3, 3] + WALL[0, 3]), 0.0, 0.0))
                    frame = simulated_zone_frame(WALL, sensor_pose(pose, TRUE), sensor_cam,
                                                 rects, 0.0, rng, mean_noise_m=0.0)
                    means.append(frame.flat()[0])
                    masks.append(frame.flat()[2])
                u = extrinsic_uncertainty(planes, means, masks, TRUE, zone_noise_m=0.02)
                rows.append((u.rotation_rms_deg, 1000 * u.translation_rms_m,
                             u.miss_probability(0.5, 0.010)))
            rot, shift, miss = np.mean(rows, axis=0)
            print(f"| {tilt[1]:g}-{tilt[0]:g} | {views} | {rot:.3f} | {shift:.1f} | "
                  f"{100 * miss:.0f} % |", flush=True)


def part_refusal() -> None:
    with tempfile.TemporaryDirectory() as tmp:
        try:
            board_run(Path(tmp) / "one", 20, 0, tilt=(3.0, 0.0))
        except ValueError as err:
            print(f"refused: {err}")
        else:
            print("NOT refused")


def part_depth(seeds: int) -> None:
    """The box-room sweep of docs/calibration.md (6 planes x 4 frames, 160x120 depth)."""
    from deltar.calibration.pipeline import calibrate_observations, observation_from_frame
    from deltar.calibration.synthetic import synthetic_rig_frames

    cam = CameraIntrinsics(150, 150, 79.5, 59.5, 160, 120)
    truth = SensorExtrinsics(Rotation.from_euler("zyx", [91.5, 2.0, -1.5], degrees=True)
                             .as_matrix(), [0.04, -0.02, 0.01])
    print("| seed | rotation error (deg) | translation error (mm) |")
    print("|---|---|---|")
    for seed in range(seeds):
        frames = synthetic_rig_frames(truth, cam, frames_per_plane=4, seed=seed)
        obs = [observation_from_frame(f.zone_frame, depth_to_points(f.depth_m, cam, 2),
                                      nominal_extrinsics(90), name=str(i))
               for i, f in enumerate(frames)]
        ext = calibrate_observations(obs, nominal_extrinsics(90), cam).calibration.extrinsics
        angle, shift = errors(ext, truth)
        print(f"| {seed} | {angle:.3f} | {shift:.2f} |", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--part", choices=("board", "intrinsics", "refusal", "depth", "bound"),
                        default="board")
    parser.add_argument("--seeds", type=int, default=5)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--tilt", default="45,25",
                        help="largest and smallest view tilt off the wall's normal, degrees")
    parser.add_argument("--views", default="15,20,25",
                        help="view counts of --part board, comma-separated")
    parser.add_argument("--zone-noise", type=float, default=0.02,
                        help="zone noise of --part board and intrinsics, metres")
    parser.add_argument("--invalid", type=float, default=0.1,
                        help="share of zones made invalid at random (board, intrinsics)")
    parser.add_argument("--near", type=int, default=0,
                        help="of the views (--part intrinsics: 20), this many 0.3-0.45 m away "
                        "(the board fills most of the image)")
    args = parser.parse_args()
    seeds = range(args.first_seed, args.first_seed + args.seeds)
    tilt = tuple(float(v) for v in args.tilt.split(","))
    zones = {"zone_noise_m": args.zone_noise, "invalid_fraction": args.invalid}
    if args.part == "board":
        part_board(seeds, tilt, tuple(int(v) for v in args.views.split(",")), near=args.near,
                   **zones)
    elif args.part == "intrinsics":
        part_intrinsics(seeds, tilt, near=args.near, **zones)
    elif args.part == "bound":
        part_bound(seeds)
    elif args.part == "refusal":
        part_refusal()
    else:
        part_depth(max(args.seeds, 6))


if __name__ == "__main__":
    main()
