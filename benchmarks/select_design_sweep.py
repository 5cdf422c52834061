"""Which design choices of the plane-select network help on rooms it never saw?

The bundled recipe learns almost nothing from data (a temperature that stays near its
start, and channel weights that change no score), so its design is its real
hyper-parameters. This script scores design variants of the ``deltar-select`` network
built from the packaged ImageNet encoder, untrained, on the simulated test sets of
``benchmarks/cross_scene.py`` (each scene's frames, network alone, no blend), and makes
the choice nested: for each of that script's five folds it picks the variant with the
lowest mean REL over the fold's eight training scenes and reports it on the two scenes
left out. The rows with a component switched off (``no_affinity``: temperature 0, the
zones' spatial prior alone; ``no_planes``: constant zone readings; ``no_flags``: the
zones that reported no target ignored) are the test-time ablation of the parts the
design keeps.

    python benchmarks/cross_scene.py --out cs/          # makes cs/sets (once)
    python benchmarks/select_design_sweep.py --sets cs/sets --out sweep.json \
        [--frames 10] [--condition clean] [--variants base t7 lite2]

Results are kept in ``--out`` (one entry per variant), so a stopped sweep resumes.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from cross_scene import FOLDS

#: name -> (affinity temperature, DeltarNet overrides of the deltar-select preset).
VARIANTS: dict[str, tuple[float, dict]] = {
    "base": (4.5, {}),
    "no_affinity": (0.0, {}),
    "no_planes": (4.5, {"planar": False}),
    "no_flags": (4.5, {"no_target_depth": None}),
    "t3": (3.0, {}),
    "t7": (7.0, {}),
    "t10": (10.0, {}),
    "strides_4_8_16": (4.5, {"descriptor_strides": (4, 8, 16)}),
    "strides_8_16_32": (4.5, {"descriptor_strides": (8, 16, 32)}),
    "strides_8": (4.5, {"descriptor_strides": (8,)}),
    "strides_16": (4.5, {"descriptor_strides": (16,)}),
    "lite1": (4.5, {"backbone": "tf_efficientnet_lite1"}),
    "lite2": (4.5, {"backbone": "tf_efficientnet_lite2"}),
}
#: Variants that switch a component off: scored, never chosen.
ABLATIONS = ("no_affinity", "no_planes", "no_flags")


def load_scenes(sets: Path, condition: str, frames: int) -> dict[str, list]:
    """Up to ``frames`` evenly spaced samples of each protocol scene's test set."""
    from deltar.data.zju_l5 import ZJUL5Dataset

    scenes = {}
    for scene in sorted({s for fold in FOLDS.values() for s in fold}):
        folder = sets / (scene if condition == "clean" else f"{scene}-{condition}")
        dataset = ZJUL5Dataset(folder / "data.json")
        picks = sorted({int(i) for i in np.linspace(0, len(dataset) - 1,
                                                      min(frames, len(dataset))).round()})
        scenes[scene] = [dataset[i] for i in picks]
    return scenes


def score_variant(temperature: float, overrides: dict, scenes: dict[str, list]
                  ) -> dict[str, list[float]]:
    """{scene: [REL, RMSE (m), d1]} of one untrained variant, means over its frames."""
    import torch

    from deltar.evaluation.metrics import depth_metrics
    from deltar.inference.estimator import DepthEstimator
    from deltar.models import create_model

    model = create_model("deltar-select", encoder_weights="imagenet", design_size=(256, 320),
                         hypothesis_sampling="icdf", **overrides)
    with torch.no_grad():
        model.head.temperature.fill_(temperature)
    estimator = DepthEstimator(model.eval(), blend=None, uncertainty=None)
    rows = {}
    for scene, samples in scenes.items():
        values = []
        for sample in samples:
            result = estimator.predict(sample.rgb, sample.zone_frame(),
                                       zone_rects=sample.zone_rects)
            metrics = depth_metrics(result.depth_m, sample.depth_m)
            values.append((metrics["rel"], metrics["rmse"], metrics["d1"]))
        rows[scene] = np.mean(values, axis=0).tolist()
    return rows


def nested_choice(results: dict[str, dict[str, list[float]]]) -> list[str]:
    """Per fold, the variant best on its training scenes, and its held-out scores."""
    lines, chosen_rel, base_rel = [], [], []
    candidates = [name for name in results if name not in ABLATIONS]
    for fold, left_out in FOLDS.items():
        def training_rel(name: str, left_out=left_out) -> float:
            return float(np.mean([v[0] for s, v in results[name].items()
                                  if s not in left_out]))
        best = min(candidates, key=training_rel)
        held = ", ".join(f"{s} {results['base'][s][0]:.4f} -> {results[best][s][0]:.4f}"
                         for s in left_out)
        lines.append(f"{fold:<20} chose {best:<16} held-out REL (base -> chosen): {held}")
        chosen_rel += [results[best][s][0] for s in left_out]
        base_rel += [results["base"][s][0] for s in left_out]
    lines.append(f"mean held-out REL: base {np.mean(base_rel):.4f}, nested choice "
                 f"{np.mean(chosen_rel):.4f}")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sets", type=Path, required=True,
                        help="the sets/ folder of a cross_scene.py run")
    parser.add_argument("--out", type=Path, required=True, help="results JSON (resumed)")
    parser.add_argument("--condition", default="clean", choices=("clean", "degraded"))
    parser.add_argument("--frames", type=int, default=10, help="frames per scene")
    parser.add_argument("--variants", nargs="+", choices=list(VARIANTS), default=list(VARIANTS))
    parser.add_argument("--threads", type=int, default=2)
    args = parser.parse_args(argv)
    if "base" not in args.variants:
        parser.error("--variants must include base (the nested choice is reported against it)")
    import torch

    torch.set_num_threads(args.threads)
    results = json.loads(args.out.read_text()) if args.out.is_file() else {}
    scenes = load_scenes(args.sets, args.condition, args.frames)
    for name in args.variants:
        if name not in results:
            start = time.perf_counter()
            results[name] = score_variant(*VARIANTS[name], scenes)
            partial = args.out.with_suffix(".partial")
            partial.write_text(json.dumps(results, indent=1))
            partial.replace(args.out)  # atomic: a stopped sweep keeps what it had
            print(f"{name}: {time.perf_counter() - start:.0f} s", flush=True)
    wanted = {name: results[name] for name in args.variants}
    header = "variant".ljust(17) + "".join(f"{s[:9]:>10}" for s in next(iter(wanted.values())))
    print(f"\nREL per scene ({args.condition}, network alone, {args.frames} frames per scene)")
    print(header + "      mean  RMSE mean")
    for name, rows in wanted.items():
        rel = [v[0] for v in rows.values()]
        rmse = [v[1] for v in rows.values()]
        print(name.ljust(17) + "".join(f"{v:>10.4f}" for v in rel)
              + f"{np.mean(rel):>10.4f}{np.mean(rmse):>11.4f}")
    print()
    print("\n".join(nested_choice(wanted)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
