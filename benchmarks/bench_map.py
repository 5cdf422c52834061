"""How good are ``deltar map``'s maps? Two shared scenes with ground-truth poses.

For each scene (TUM fr3 cabinet: 58 keyframes; 7-Scenes red kitchen: every 10th of its
500 frames), a recording is written with simulated L5 zones (8x8, from the ground-truth
depth), the ground-truth depth and the ground-truth poses
(``deltar.mapping.scenes.write_posed_recording``). Then ``deltar map`` builds, with the
same poses and settings:

- the reference map from the ground-truth depth (``--method recorded``);
- the model's map, from a model that never saw the scene (the bundled ``default`` trained
  on both): on each scene a fold model of ``benchmarks/cross_scene.py`` trained without
  it (``--kitchen-model``: the kitchen-shelf fold's; ``--cabinet-model``: the
  cabinet-makerspace fold's; their ``model-calibrated.pt`` carry the fold's fitted blend
  and sigma);
- the same model with the estimator's confidence blend with the colorization fill
  (``--blend``; ``deltar map`` fuses the network's own depth by default);
- every classical baseline's map (``--method NAME``).

Each map's surface points are scored against the reference map's
(``deltar.mapping.metrics.map_scores``: accuracy, completeness, precision / recall /
F-score at 5 and 10 cm). Also measured: the integration speed without depth prediction
at 480x640 on 2 threads (ratio to Open3D's own unweighted ``integrate`` in the same run),
each run's peak memory (max RSS), and the cabinet mapped with RGB-D odometry instead of
the given poses (ATE).

    python benchmarks/bench_map.py --out map-bench/ \\
        --kitchen-model cs/runs/without-kitchen-shelf/model-calibrated.pt \\
        --cabinet-model cs/runs/without-cabinet-makerspace/model-calibrated.pt

Everything is written to ``--out`` (recordings, maps, results.json, the pictures of the
meshes side by side); finished maps are reused when the script is run again.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

PROJECT = Path(__file__).resolve().parents[1]
DATA = PROJECT.parent / "shared" / "data" / "rgbd"
BASELINES = ("median", "nearest", "bilinear", "bicubic", "guided_filter", "joint_bilateral",
             "colorization")
#: name -> (folder, frame step)
SCENES = {"cabinet": ("tum_fr3_cabinet", 1), "kitchen": ("7scenes_redkitchen", 10)}
SETTINGS = ["--voxel", "0.02", "--truncation", "4"]


def make_recording(out: Path, scene: str) -> Path:
    """The scene as a recording with simulated zones and its poses (made once)."""
    from deltar.data.rgbd import open_rgbd
    from deltar.mapping.scenes import scene_poses, write_posed_recording

    folder, step = SCENES[scene]
    target = out / "recordings" / scene
    if (target / "zones.jsonl").is_file():
        return target
    source = open_rgbd(DATA / folder)
    indices = list(range(0, len(source), step))
    poses = scene_poses(DATA / folder, [source.names[i] for i in indices])
    frames = ((source[i].image, source[i].depth_m, pose)
              for i, pose in zip(indices, poses, strict=True))
    print(f"writing {target} ({len(indices)} frames)", flush=True)
    return write_posed_recording(target, frames, source.intrinsics)


def run_map(recording: Path, out: Path, args: list[str]) -> dict:
    """``deltar map`` in a child process; its map.json plus wall time and peak RSS."""
    if (out / "map.json").is_file():
        summary = json.loads((out / "map.json").read_text())
        if "peak_rss_mib" in summary:
            return summary
    # --threads sets the model's threads: deltar map refuses it with a --method.
    threads = [] if "--method" in args else ["--threads", "2"]
    command = [sys.executable, "-m", "deltar", "map", str(recording), "--out", str(out),
               "--overwrite", *threads, *SETTINGS, *args]
    print("$", " ".join(command[2:]), flush=True)
    start = time.perf_counter()
    child = subprocess.Popen(command, cwd=PROJECT)
    _, status, usage = os.wait4(child.pid, 0)
    if status != 0:
        raise SystemExit(f"deltar map failed ({status}): {' '.join(command)}")
    summary = json.loads((out / "map.json").read_text())
    summary["wall_s"] = time.perf_counter() - start
    summary["peak_rss_mib"] = usage.ru_maxrss / 1024  # kilobytes on Linux
    (out / "map.json").write_text(json.dumps(summary, indent=2) + "\n")
    return summary


def read_points(path: Path) -> np.ndarray:
    from deltar.io.ply import read_ply

    return read_ply(path).points


def integration_speed(recording: Path, frames: int = 40) -> dict:
    """Frames/s of TSDFMap.integrate at 480x640 on 2 threads vs Open3D's integrate."""
    import torch

    from deltar.mapping.frames import FrameSource
    from deltar.mapping.poses import match_poses, read_pose_folder
    from deltar.mapping.tsdf import MapSettings, TSDFMap, require_open3d

    torch.set_num_threads(2)
    o3d = require_open3d()
    import open3d.core as o3c

    source = FrameSource(recording, limit=frames)
    loaded = [(f.image.copy(), f.recorded_depth_m.copy(), f.calibration.intrinsics, f.name)
              for f in source.load()]
    trajectory = read_pose_folder(recording / "pose")
    poses, _ = match_poses(trajectory, np.zeros(len(loaded)), [f[3] for f in loaded])
    weight = np.ones(loaded[0][1].shape, np.float32)
    settings = MapSettings(voxel_size_m=0.02, truncation_voxels=4, max_depth_m=4.0)
    ours = TSDFMap(settings)
    start = time.perf_counter()
    for (image, depth, intrinsics, _), pose in zip(loaded, poses, strict=True):
        ours.integrate(depth, image, weight, intrinsics, pose)
    ours_s = time.perf_counter() - start
    # Open3D's own integration (every pixel weight 1) in the same run, as the reference.
    grid = o3d.t.geometry.VoxelBlockGrid(("tsdf", "weight", "color"),
                                         (o3c.float32, o3c.float32, o3c.float32),
                                         ((1), (1), (3)), 0.02, 8, 20000)
    start = time.perf_counter()
    for (image, depth, intrinsics, _), pose in zip(loaded, poses, strict=True):
        extrinsic = o3c.Tensor(np.linalg.inv(pose))
        depth_image = o3d.t.geometry.Image(o3c.Tensor(np.ascontiguousarray(depth)))
        k = o3c.Tensor(intrinsics.matrix)
        blocks = grid.compute_unique_block_coordinates(depth_image, k, extrinsic, 1.0, 4.0, 4.0)
        grid.integrate(blocks, depth_image,
                       o3d.t.geometry.Image(o3c.Tensor(image.astype(np.float32))), k,
                       extrinsic, 1.0, 4.0, 4.0)
    native_s = time.perf_counter() - start
    height, width = loaded[0][1].shape
    return {"frames": len(loaded), "size": f"{height}x{width}", "threads": 2,
            "fps": len(loaded) / ours_s, "open3d_integrate_fps": len(loaded) / native_s,
            "ratio_to_open3d": native_s / ours_s, "blocks": ours.block_count}


def picture(out: Path, scene: str, maps: dict[str, Path], path: Path) -> None:
    """The maps' coloured surface points side by side, seen from above-front (matplotlib)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from deltar.io.ply import read_ply

    fig = plt.figure(figsize=(4.2 * len(maps), 4.2))
    for i, (name, ply) in enumerate(maps.items()):
        cloud = read_ply(ply)
        rng = np.random.default_rng(0)
        keep = rng.permutation(len(cloud.points))[:60000]
        xyz, rgb = cloud.points[keep], cloud.colors[keep] / 255.0
        ax = fig.add_subplot(1, len(maps), i + 1, projection="3d")
        ax.scatter(xyz[:, 0], xyz[:, 1], xyz[:, 2], c=rgb, s=0.3, linewidths=0)
        ax.set_title(name, fontsize=10)
        ax.set_axis_off()
        ax.view_init(elev=25, azim=-60)
        ax.set_box_aspect(np.ptp(xyz, axis=0))
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--kitchen-model", type=Path, required=True,
                        help="a checkpoint trained without the 7-Scenes kitchen")
    parser.add_argument("--cabinet-model", type=Path, required=True,
                        help="a checkpoint trained without the TUM fr3 cabinet")
    parser.add_argument("--scenes", default="cabinet,kitchen")
    parser.add_argument("--baselines", default=",".join(BASELINES))
    args = parser.parse_args(argv)
    from deltar.mapping.metrics import map_scores

    results: dict = {}
    for scene in args.scenes.split(","):
        recording = make_recording(args.out, scene)
        maps_dir = args.out / "maps" / scene
        model = ["--checkpoint", str(args.kitchen_model if scene == "kitchen"
                                     else args.cabinet_model)]
        runs = {"ground truth": ["--method", "recorded"], "model": model,
                "model_blend": [*model, "--blend"]}
        runs |= {name: ["--method", name] for name in args.baselines.split(",")}
        summaries = {name: run_map(recording, maps_dir / name.replace(" ", "_"), extra)
                     for name, extra in runs.items()}
        reference = read_points(maps_dir / "ground_truth" / "points.ply")
        rows = {}
        for name, summary in summaries.items():
            if name == "ground truth":
                continue
            rows[name] = map_scores(read_points(maps_dir / name / "points.ply"), reference)
            rows[name] |= {"peak_rss_mib": summary["peak_rss_mib"],
                           "depth_s_per_frame": summary["depth_s"] / summary["frames"],
                           "integrate_fps": summary["frames"] / summary["integrate_s"]}
        results[scene] = {"frames": summaries["model"]["frames"],
                          "model": summaries["model"]["depth"], "scores": rows,
                          "reference_peak_rss_mib": summaries["ground truth"]["peak_rss_mib"]}
        best = max(BASELINES, key=lambda b: rows[b]["fscore_5"]) if all(
            b in rows for b in BASELINES) else None
        shown = {"ground truth": maps_dir / "ground_truth" / "points.ply",
                 "model": maps_dir / "model" / "points.ply"}
        if best is not None:
            shown[f"best baseline ({best})"] = maps_dir / best / "points.ply"
        picture(args.out, scene, shown, args.out / f"maps_{scene}.png")
        if scene == "cabinet":
            odometry = run_map(recording, args.out / "maps" / "cabinet_odometry" / "model",
                               ["--odometry"])
            results["cabinet_odometry"] = {k: odometry[k] for k in
                                           ("ate_m", "odometry", "frames", "peak_rss_mib")}
            # The odometry map is in the first camera's frame: put it at that camera's
            # true pose to score it against the reference (drift then shows as error).
            from deltar.mapping.poses import match_poses, read_pose_folder

            first = np.loadtxt(args.out / "maps" / "cabinet_odometry" / "model" /
                               "trajectory.txt")[0]
            found = read_pose_folder(recording / "pose")
            anchor = match_poses(found, np.array([first[0]]),
                                 [str(round(first[0] * 1e9))])[0][0]
            points = read_points(args.out / "maps" / "cabinet_odometry" / "model" /
                                 "points.ply")
            results["cabinet_odometry"]["scores"] = map_scores(
                points @ anchor[:3, :3].T + anchor[:3, 3], reference)
            results["integration_speed"] = integration_speed(recording)
        print(json.dumps(results, indent=1), flush=True)
    (args.out / "results.json").write_text(json.dumps(results, indent=2) + "\n")
    print(markdown(results))
    return 0


def markdown(results: dict) -> str:
    """The results as the RESULTS.md tables."""
    lines = []
    for scene in ("cabinet", "kitchen"):
        if scene not in results:
            continue
        r = results[scene]
        lines += [f"{scene} ({r['frames']} frames; model: {r['model']})", "",
                  "| depth | acc cm | comp cm | P@5 | R@5 | F@5 | F@10 | peak RSS MiB |",
                  "|---|---|---|---|---|---|---|---|"]
        for name, s in sorted(r["scores"].items(), key=lambda kv: -kv[1]["fscore_5"]):
            lines.append(f"| {name} | {100 * s['accuracy_m']:.1f} | "
                         f"{100 * s['completeness_m']:.1f} | {s['precision_5']:.3f} | "
                         f"{s['recall_5']:.3f} | {s['fscore_5']:.3f} | {s['fscore_10']:.3f} | "
                         f"{s['peak_rss_mib']:.0f} |")
        lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    raise SystemExit(main())
