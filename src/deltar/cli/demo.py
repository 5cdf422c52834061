"""``deltar demo``: the whole path on generated scenes, with nothing to download.

Renders procedural rooms (the package bundles no third-party images), simulates the
L5 zone readings, runs every classical baseline (and the bundled model when the package
ships one), and writes per-frame panels, the metrics table and a JSON of the metrics.
"""

from __future__ import annotations

from pathlib import Path

import typer


def write_predict_sample(data_json: Path, folder: Path) -> None:
    """Write the first frame of a ZJU-L5-layout set as ``deltar predict`` inputs.

    Creates ``folder/image.png`` (RGB), ``folder/zones.json`` (zone frame) and
    ``folder/calib.json`` (the frame's camera intrinsics, identity sensor extrinsic), so
    ``deltar predict --image ... --zones ... --calib ...`` runs on it.
    """
    import cv2

    from deltar.calibration.rig import RigCalibration
    from deltar.data.zju_l5 import ZJUL5Dataset
    from deltar.io.atomic import atomic_path
    from deltar.io.zone_file import save_zone_frame
    from deltar.sensor.geometry import SensorExtrinsics

    sample = ZJUL5Dataset(data_json)[0]
    frame = sample.zone_frame()
    folder.mkdir(parents=True, exist_ok=True)
    with atomic_path(folder / "image.png", overwrite=False) as tmp:
        if not cv2.imwrite(str(tmp), cv2.cvtColor(sample.rgb, cv2.COLOR_RGB2BGR)):
            raise OSError(f"could not write {folder / 'image.png'}")
    save_zone_frame(folder / "zones.json", frame)
    RigCalibration(intrinsics=sample.intrinsics, extrinsics=SensorExtrinsics(),
                   grid=frame.grid).save(folder / "calib.json")


def demo(
    out: Path = typer.Argument(Path("deltar-demo"), help="Output folder (created; must not "
                               "already hold a demo)."),
    frames: int = typer.Option(6, "--frames", min=1, help="Number of generated scenes."),
    seed: int = typer.Option(2022, "--seed", help="Seed of the procedural scenes."),
    size: str = typer.Option("480x640", "--size", help="Image size HxW in pixels."),
) -> None:
    """Simulate L5 readings over generated rooms and compare depth methods on them.

    Writes OUT/scenes (a ZJU-L5-layout set), OUT/panels (one PNG per frame and method),
    OUT/metrics.json and OUT/sample (image.png, zones.json, calib.json: inputs for
    'deltar predict'); prints the paper's metrics table.
    """
    from deltar.cli.checks import image_size, output_folder
    from deltar.cli.evaluate import evaluate
    from deltar.data.procedural import ProceduralReader
    from deltar.data.simulated import simulate_set

    height, width = image_size(size, "--size", minimum=8)
    output_folder(out, "OUT")
    scenes = out / "scenes"
    if (scenes / "data.json").exists():
        if (out / "metrics.json").exists():
            raise typer.BadParameter(f"{out} already holds a demo; choose another folder",
                                     param_hint="OUT")
        raise typer.BadParameter(f"{out} holds an unfinished demo (no metrics.json: it was "
                                 "interrupted); remove it or choose another folder",
                                 param_hint="OUT")
    simulate_set(ProceduralReader(frames, seed, height, width), scenes, scene="procedural")
    write_predict_sample(scenes / "data.json", out / "sample")
    from deltar.weights import bundled_model_names

    evaluate(method="all", checkpoint=bundled_model_names(), official=None,
             data=scenes / "data.json", split="test",
             json_out=out / "metrics.json", save_vis=out / "panels", limit=None,
             min_depth=1e-3, max_depth=10.0, flip=False, network=False, overwrite=False)
