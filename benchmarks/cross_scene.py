"""Leave scenes out: does a recipe beat the classical methods on rooms it never saw?

The ten scenes of ../shared/data/rgbd form five folds of two scenes each (a room-scale
scene with a close-range one, so every fold trains on both kinds). For each fold: train
the recipe (a training config, ``configs/cross_scene_select.yaml`` by default) on the
eight other scenes with ``deltar train``, simulate each left-out scene's zones with
``deltar simulate`` -- clean; degraded (20% of the valid zones dropped, 30% of the rest
biased by N(+0.10, 0.15) m); and without no-target flags (as the released ZJU-L5 files
store them) -- and score every classical baseline and the trained model on it with
``deltar evaluate``, each baseline also in its ``+far`` form (zones that reported no
target read as 5 m, the model's prior). The model is scored twice: ``trained``, as
``DepthEstimator`` runs it (for the plane-select recipe: blended with the colorization
fill where the network is unsure), and ``network``, the network alone (``+network``).
Prints each scene's table and the mean over scenes (each scene weighs the same), with
both rows' REL and RMSE change against the best classical baseline of each scene and
against the best ``+far`` one; on the means against the baseline best on the means, the
best of each fold and the best of each scene.

    python benchmarks/cross_scene.py --out cross-scene/           # all five folds
    python benchmarks/cross_scene.py --out cs/ --folds kitchen-shelf --steps 100  # a look
    python benchmarks/cross_scene.py --out cs/ --extra-model default      # + bundled model
    python benchmarks/cross_scene.py --out cross-scene/ --max-depth 4  # the sensor's range only

Each step's output is kept in ``--out`` (test sets, runs, metrics), so an interrupted
protocol resumes where it stopped; a fold whose ``model.pt`` exists is not retrained.
"""

from __future__ import annotations

import argparse
import copy
import json
import subprocess
import sys
import time
from pathlib import Path

import yaml

PROJECT = Path(__file__).resolve().parents[1]
DATA = PROJECT.parent / "shared" / "data" / "rgbd"

#: name -> (folder, intrinsics "fx,fy,cx,cy" or None for the folder's own, test-frame
#: step). The steps keep each test set near 50 frames or fewer (neighbouring frames are
#: near duplicates); every scene weighs the same in the means.
SCENES: dict[str, tuple[str, str | None, int]] = {
    "kitchen": ("7scenes_redkitchen", None, 10),
    "office": ("realsense_office", "615,615,320,240", 2),
    "icl": ("icl_livingroom1", "525,525,319.5,239.5", 4),
    "floor": ("realsense_floor", "617.25,617.55,317.39,245.98", 1),
    "cabinet": ("tum_fr3_cabinet", None, 1),
    "makerspace": ("cmu_makerspace", None, 1),
    "shelf": ("apc_shelf", None, 1),
    "totes": ("arc_totes", None, 1),
    "lab_table": ("graspnet_lab_table", None, 1),
    "table": ("graspnet_1billion_table", None, 1),
}
#: fold name -> the scenes it leaves out; together the folds test every scene once.
FOLDS: dict[str, tuple[str, ...]] = {
    "kitchen-shelf": ("kitchen", "shelf"),
    "office-totes": ("office", "totes"),
    "icl-lab_table": ("icl", "lab_table"),
    "floor-table": ("floor", "table"),
    "cabinet-makerspace": ("cabinet", "makerspace"),
}
#: The test conditions: deltar simulate options of each.
CONDITIONS: dict[str, list[str]] = {
    "clean": [],
    "degraded": ["--drop-fraction", "0.2", "--bias-prob", "0.3", "--bias-mean", "0.10",
                 "--bias-std", "0.15"],
    "noflags": ["--without-no-target-flags"],
}
BASELINES = ("median", "nearest", "bilinear", "bicubic", "guided_filter", "joint_bilateral",
             "colorization")
#: The same baselines reading the zones that reported no target at 5 m (the model's prior):
#: what a classical method gains from that flag alone.
FAR_BASELINES = tuple(name + "+far" for name in BASELINES)
METRICS = ("d1", "rel", "rmse", "log10")
#: Frames of each training scene (clean and degraded) a fold's output stage is fitted on
#: (scenes with fewer give all theirs). Six left the fitted zone rules to near-ties (the
#: no-target threshold of one fold: 0.0908 against 0.0910, RESULTS.md 2026-12-05).
CALIBRATION_FRAMES = 12
#: Uncertainty coverage of the model rows (fractions within one and two sigma).
COVERAGE = ("within_1sigma", "within_2sigma")


def deltar(*args: str) -> None:
    """Run one ``deltar`` command in this Python, failing loudly."""
    command = [sys.executable, "-m", "deltar", *args]
    print("$", " ".join(command[2:]), flush=True)
    subprocess.run(command, check=True, cwd=PROJECT)


def test_set(out: Path, scene: str, condition: str, targets: int = 1) -> Path:
    """The left-out scene's simulated test set (data.json) in one condition, made once
    (``targets``: targets per zone the simulated sensor reports)."""
    folder, intrinsics, step = SCENES[scene]
    target = out / "sets" / (scene if condition == "clean" else f"{scene}-{condition}")
    index = target / "data.json"
    if not index.is_file():
        args = ["simulate", str(DATA / folder), str(target), "--step", str(step),
                "--targets", str(targets)]
        if intrinsics:
            args += ["--intrinsics", intrinsics]
        deltar(*args, *CONDITIONS[condition])
    return index


def has_no_target_flags(index: Path) -> bool:
    """Whether any frame of a simulated set has a zone flagged as no target."""
    from deltar.data.zju_l5 import ZJUL5Dataset

    return any(sample.zone_no_target is not None and sample.zone_no_target.any()
               for sample in ZJUL5Dataset(index))


def fold_config(template: dict, fold: str, steps: int | None) -> dict:
    """The recipe with the fold's left-out scenes removed from its training sources."""
    config = copy.deepcopy(template)
    folders = {SCENES[scene][0] for scene in FOLDS[fold]}
    kept = [s for s in config["data"]["sources"]
            if Path(str(s.get("path", ""))).name not in folders]
    train = [s for s in kept if s.get("role", "train_val") in ("train", "train_val")]
    if not train:
        raise SystemExit(f"the recipe has no training source besides {sorted(folders)}")
    if not any(s.get("role") == "val" for s in kept):
        # Validation is a sanity check only: a few frames of the first training scene.
        kept.append({**train[0], "role": "val", "every": 50})
    config["data"]["sources"] = kept
    config["name"] = f"{config.get('name', 'run')}-without-{fold}"
    if steps is not None:
        config["trainer"]["max_steps"] = steps
    return config


def train_fold(out: Path, template: dict, fold: str, steps: int | None) -> tuple[Path, float]:
    """Train the fold's model (unless done); return its model.pt and the wall time (s)."""
    run_dir = out / "runs" / f"without-{fold}"
    model = run_dir / "model.pt"
    if model.is_file():
        return model, float("nan")
    config_path = out / "configs" / f"without-{fold}.yaml"
    config_path.parent.mkdir(parents=True, exist_ok=True)
    config_path.write_text(yaml.safe_dump(fold_config(template, fold, steps), sort_keys=False))
    started = time.monotonic()
    if (run_dir / "checkpoints" / "last.ckpt").is_file():
        # A folder left by an interrupted run resumes from its last checkpoint (with the
        # config it saved).
        deltar("train", "--resume", str(run_dir))
    else:
        deltar("train", "-c", str(config_path), "--run-dir", str(run_dir))
    return model, time.monotonic() - started


def _evaluated(result: Path, args: list[str], wanted: set[str]) -> dict[str, dict]:
    """Metrics in ``result``, running ``deltar evaluate ARGS --json result`` unless it
    already holds every method of ``wanted`` (then it is kept: the protocol resumes)."""
    stale = result.is_file() and not wanted <= set(json.loads(result.read_text()))
    if not result.is_file() or stale:
        result.parent.mkdir(parents=True, exist_ok=True)
        deltar(*args, "--json", str(result), *(["--overwrite"] if stale else []))
    return json.loads(result.read_text())


def evaluate(out: Path, index: Path, models: dict[str, str], tag: str,
             max_depth: float | None = None) -> dict[str, dict]:
    """``deltar evaluate`` of every baseline and model on one set; {method: metrics}.

    Baselines and models are kept in two files, so a changed model re-runs only itself.
    ``max_depth`` (metres) scores only ground truth nearer than it, kept apart in
    ``metrics-max<M>/``; None: evaluate's default range (10 m, the paper's).
    """
    methods = BASELINES + FAR_BASELINES
    folder = out / ("metrics" if max_depth is None else f"metrics-max{max_depth:g}")
    depth = [] if max_depth is None else ["--max-depth", f"{max_depth:g}"]
    rows = _evaluated(folder / f"{tag}.json",
                      ["evaluate", "--data", str(index), "--method", ",".join(methods),
                       *depth], set(methods))
    rows = {name: rows[name] for name in methods}
    wanted = {f"model:{path}" for path in models.values()}
    args = ["evaluate", "--data", str(index), *depth]
    for path in models.values():
        args += ["--checkpoint", path]
    found = _evaluated(folder / f"{tag}.models.json", args, wanted)
    for label, path in models.items():
        rows[label] = found[f"model:{path}"]
    return rows


def calibration_set(out: Path, scene: str, condition: str,
                    frames: int = CALIBRATION_FRAMES, targets: int = 1) -> Path:
    """A few frames of a training scene (clean or degraded), made once: what a fold's
    output stage is fitted on (the fold's own training scenes only).

    Raises:
        SystemExit: the folder already holds this set with another number of frames (a
            run resumed with another ``--calibration-frames``).
    """
    from deltar.data.rgbd import open_rgbd

    folder, intrinsics, _ = SCENES[scene]
    target = out / "calibration-sets" / (scene if condition == "clean"
                                         else f"{scene}-{condition}")
    index = target / "data.json"
    available = len(open_rgbd(DATA / folder).names)
    if index.is_file():
        held = sum(len(names) for names in json.loads(index.read_text()).values())
        if held != min(frames, available):
            raise SystemExit(f"{index} holds {held} frames, not the {min(frames, available)} "
                             f"of --calibration-frames {frames}: use another --out")
    else:
        step = max(1, available // frames)
        args = ["simulate", str(DATA / folder), str(target), "--step", str(step),
                "--limit", str(frames), "--targets", str(targets)]
        if intrinsics:
            args += ["--intrinsics", intrinsics]
        deltar(*args, *CONDITIONS[condition])
    return index


def calibrate_fold(out: Path, fold: str, model: Path, targets: int = 1,
                   frames: int = CALIBRATION_FRAMES, detector: bool = False) -> Path:
    """The fold's model with its output stage (zone outlier rule, blend, sigma,
    no-target rules) fitted on ``frames`` frames of each of its training scenes, clean
    and degraded (made once); with ``detector`` a learned zone outlier detector is
    among the outlier candidates."""
    calibrated = model.with_name("model-calibrated.pt")
    if not calibrated.is_file():
        args = ["fit-uncertainty", str(model), "--out", str(calibrated)]
        if detector:
            args += ["--detector-noise", ",".join(CONDITIONS["degraded"][1::2])]
        for scene in SCENES:
            if scene not in FOLDS[fold]:
                for condition in ("clean", "degraded"):
                    args += ["--data", str(calibration_set(out, scene, condition, frames,
                                                           targets))]
                if detector:  # it learns the degraded condition's noise on clean frames
                    args += ["--detector-data", str(calibration_set(
                        out, scene, "clean", frames, targets))]
        deltar(*args)
    return calibrated


def table(title: str, rows: dict[str, dict]) -> str:
    """A plain-text table of d1 / REL / RMSE / log10, one row per method."""
    columns = METRICS + COVERAGE
    lines = [title, f"{'method':<18}" + "".join(f"{m[:9]:>10}" for m in columns)]
    for name, metrics in rows.items():
        lines.append(f"{name:<18}" + "".join(f"{metrics[m]:>10.3f}" if m in metrics else
                                             f"{'-':>10}" for m in columns))
    return "\n".join(lines)


def model_argument(name_or_path: str) -> str:
    """An ``--extra-model`` as the deltar commands (run in the project root) must get it:
    a bundled name as it is, a file relative to the caller's folder made absolute."""
    path = Path(name_or_path)
    return str(path.resolve()) if path.exists() else name_or_path


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--config", type=Path, default=PROJECT / "configs" /
                        "cross_scene_select.yaml", help="the recipe (a deltar train config)")
    parser.add_argument("--out", type=Path, required=True, help="working folder")
    parser.add_argument("--folds", nargs="+", choices=sorted(FOLDS), default=list(FOLDS),
                        help="folds to run (default: all five)")
    parser.add_argument("--conditions", nargs="+", choices=list(CONDITIONS),
                        default=list(CONDITIONS), help="test conditions (default: all)")
    parser.add_argument("--steps", type=int, default=None,
                        help="override the recipe's trainer.max_steps")
    parser.add_argument("--targets", type=int, default=4, choices=range(1, 5),
                        help="targets per zone the simulated sensor reports (test and "
                        "calibration sets; default 4, the sensor's largest setting and "
                        "what the reported tables use; 1: the primary reading alone)")
    parser.add_argument("--calibration-frames", type=int, default=CALIBRATION_FRAMES,
                        help="frames of each training scene, clean and degraded, the "
                        f"fold's output stage is fitted on (default {CALIBRATION_FRAMES})")
    parser.add_argument("--outlier-detector", action="store_true",
                        help="also offer each fold's output-stage fit a zone outlier detector "
                        "trained on its clean calibration frames (deltar fit-uncertainty "
                        "--detector-data); folds already calibrated keep their fit")
    parser.add_argument("--extra-model", action="append", default=[], metavar="NAME_OR_PATH",
                        help="also evaluate this checkpoint (e.g. 'default') on every fold")
    parser.add_argument("--max-depth", type=float, default=None, metavar="M",
                        help="score only ground truth nearer than M metres (e.g. 4, the "
                             "sensor's range; default: deltar evaluate's 10 m, the paper's); "
                             "metrics and summaries are kept apart (metrics-max<M>/, "
                             "summary-max<M>.*)")
    args = parser.parse_args(argv)
    if args.max_depth is not None and not 0 < args.max_depth < float("inf"):
        parser.error(f"--max-depth must be a positive number of metres, got {args.max_depth}")
    if args.calibration_frames < 1:
        parser.error(f"--calibration-frames must be >= 1, got {args.calibration_frames}")
    template = yaml.safe_load(args.config.read_text())
    # The deltar commands run in the project root: a relative --out is the caller's.
    args.out = args.out.resolve()
    args.out.mkdir(parents=True, exist_ok=True)

    summary: dict[str, dict] = {"train_seconds": {}}
    scenes = [scene for fold in args.folds for scene in FOLDS[fold]]
    for fold in args.folds:
        model, seconds = train_fold(args.out, template, fold, args.steps)
        summary["train_seconds"][fold] = seconds
        # Same weights, sigma calibrated on the fold's training scenes: the depth metrics
        # are the model's, the coverage ones the calibration's.
        model = calibrate_fold(args.out, fold, model, args.targets, args.calibration_frames,
                               args.outlier_detector)
        # "trained" is the estimator as users run it (for the plane-select recipe: the
        # network blended with the colorization fill where it is unsure); "network" is the
        # network's own depth (the estimator without the blend).
        models = {"trained": str(model), "network": f"{model}+network"}
        models.update({f"extra:{name}": model_argument(name) for name in args.extra_model})
        for scene in FOLDS[fold]:
            summary[scene] = {}
            for condition in args.conditions:
                if condition == "noflags" and "clean" in summary[scene] and \
                        not has_no_target_flags(test_set(args.out, scene, "clean",
                                                         args.targets)):
                    # No zone of the scene reports no target: the same set as clean.
                    summary[scene][condition] = summary[scene]["clean"]
                    continue
                index = test_set(args.out, scene, condition, args.targets)
                tag = scene if condition == "clean" else f"{scene}-{condition}"
                summary[scene][condition] = evaluate(args.out, index, models, tag,
                                                     args.max_depth)

    report = []
    for condition in args.conditions:
        mean_rows: dict[str, dict[str, float]] = {}
        for scene in scenes:
            rows = summary[scene][condition]
            report.append(table(f"\n[{condition}] left out: {scene}", rows))
            for name, metrics in rows.items():
                for metric in (m for m in METRICS + COVERAGE if m in metrics):
                    mean_rows.setdefault(name, {}).setdefault(metric, 0.0)
                    mean_rows[name][metric] += metrics[metric] / len(scenes)
        report.append(table(f"\n[{condition}] mean over scenes {scenes}", mean_rows))
        for label, group in (("the best classical baseline", BASELINES),
                             ("the best +far baseline", FAR_BASELINES)):
            for row in ("trained", "network"):
                report.append(_comparison(label, group,
                                          [summary[s][condition] for s in scenes],
                                          mean_rows, row,
                                          [len(FOLDS[fold]) for fold in args.folds]))
        summary[f"mean_{condition}"] = mean_rows
    text = "\n".join(report)
    print(text)
    stem = "summary" if args.max_depth is None else f"summary-max{args.max_depth:g}"
    (args.out / f"{stem}.txt").write_text(text + "\n")
    (args.out / f"{stem}.md").write_text(markdown(summary, scenes, args.conditions) + "\n")
    (args.out / f"{stem}.json").write_text(json.dumps(summary, indent=2) + "\n")
    return 0


def markdown(summary: dict, scenes: list[str], conditions: list[str]) -> str:
    """Markdown tables, one per condition: a row per scene and the mean over scenes;
    the best classical and ``+far`` baselines (REL / RMSE, which), the model rows
    (d1 / REL / RMSE) and the calibrated sigma's coverage (within one / two sigma)."""
    out = []

    def best(rows: dict, group: tuple[str, ...], key: str) -> str:
        name = min(group, key=lambda b: rows[b][key])
        return f"{rows[name][key]:.3f} ({name})"

    def cells(rows: dict, name: str) -> str:
        m = rows[name]
        return f"{m['d1']:.3f} / {m['rel']:.3f} / {m['rmse']:.3f}"

    for condition in conditions:
        out += [f"{condition}:", "", "| scene | best classical REL | best classical RMSE | "
                "best +far REL | best +far RMSE | trained d1 / REL / RMSE | network d1 / "
                "REL / RMSE | trained within 1 / 2 sigma |", "|---" * 8 + "|"]
        for scene in [*scenes, "mean"]:
            rows = summary[f"mean_{condition}"] if scene == "mean" else \
                summary[scene][condition]
            cover = rows["trained"]
            coverage = (f"{cover['within_1sigma']:.3f} / {cover['within_2sigma']:.3f}"
                        if "within_1sigma" in cover else "-")
            out.append(f"| {scene} | {best(rows, BASELINES, 'rel')} | "
                       f"{best(rows, BASELINES, 'rmse')} | {best(rows, FAR_BASELINES, 'rel')} "
                       f"| {best(rows, FAR_BASELINES, 'rmse')} | {cells(rows, 'trained')} | "
                       f"{cells(rows, 'network')} | {coverage} |")
        out.append("")
    return "\n".join(out)


def _comparison(label: str, group: tuple[str, ...], folds: list[dict], mean_rows: dict,
                row: str = "trained", fold_sizes: list[int] | None = None) -> str:
    """One line: the ``row`` method's REL and RMSE gain over the best of ``group``.

    Per scene against that scene's best; on the means against the best of the group's
    rows of the mean over scenes, and the count of scenes better in both. With
    ``fold_sizes`` (consecutive scenes of ``folds`` per fold) also the mean against
    each fold's best (the method of ``group`` with the lowest mean over the fold's
    scenes) and against each scene's best, both stricter than the means' best.
    """
    gains: dict[str, list[float]] = {"rel": [], "rmse": []}
    for rows in folds:
        for key in gains:
            gains[key].append(1.0 - rows[row][key] / min(rows[b][key] for b in group))
    best = {k: min(mean_rows[b][k] for b in group) for k in gains}
    both = sum(rel > 0 and rmse > 0
               for rel, rmse in zip(gains["rel"], gains["rmse"], strict=True))
    line = (f"{row} vs {label} (+ = {row} better), per scene: REL {_percent(gains['rel'])}, "
            f"RMSE {_percent(gains['rmse'])}; better in both on {both} of {len(folds)}; on "
            f"the means: REL {100 * (1 - mean_rows[row]['rel'] / best['rel']):+.1f}%, RMSE "
            f"{100 * (1 - mean_rows[row]['rmse'] / best['rmse']):+.1f}%")
    if fold_sizes:
        if sum(fold_sizes) != len(folds):
            raise ValueError(f"fold_sizes {fold_sizes} do not add up to the {len(folds)} "
                             f"scenes")
        stricter = {"fold": {}, "scene": {}}
        for key in gains:
            fold_best, scene_best, start = [], [], 0
            for size in fold_sizes:
                part = folds[start:start + size]
                chosen = min(group, key=lambda b, part=part: sum(r[b][key] for r in part))
                fold_best += [r[chosen][key] for r in part]
                scene_best += [min(r[b][key] for b in group) for r in part]
                start += size
            model = sum(r[row][key] for r in folds)
            stricter["fold"][key] = 1.0 - model / sum(fold_best)
            stricter["scene"][key] = 1.0 - model / sum(scene_best)
        line += "".join(f"; against each {kind}'s best: REL {100 * g['rel']:+.1f}%, RMSE "
                        f"{100 * g['rmse']:+.1f}%" for kind, g in stricter.items())
    return line


def _percent(values: list[float]) -> str:
    return "[" + ", ".join(f"{100 * v:+.1f}%" for v in values) + "]"


if __name__ == "__main__":
    raise SystemExit(main())
