"""Sweep of malformed inputs over every command and the Python API, with a verdict each.

Usage::

    PYTHONPATH=src python benchmarks/bad_input_sweep.py [--verbose] [--only NAME]

Builds small inputs in a temporary folder (tiny images, zone files, a simulated
recording, a two-frame ZJU-L5 set, a synthetic calibration recording), runs each case
in-process (commands through typer's ``CliRunner``, API calls directly) and classifies
the outcome:

- ``clear``: an error whose message contains the case's key words (the argument or
  file it names and what is wrong) and none of its forbidden words;
- ``correct``: a valid input that succeeded (with the expected warning, if any);
- ``traceback``: an exception escaped (a user saw a Python traceback);
- ``silent``: a bad input was accepted without an error (or without the expected
  warning): a wrong answer;
- ``misleading``: an error whose message lacks the key words or has forbidden ones.

Besides the verdict, three flags are counted: ``late`` (a command's error came only
after the network was built, for inputs that can be checked before), ``partial`` (an output or
temporary file was left behind by a failed run) and ``modified`` (an input file
changed). Cases use ``--preset deltar-lite`` (random weights) to stay fast; the sweep
takes a few minutes on two cores. The script works on older versions of the package
too (it only uses the CLI and long-standing API calls), so the same sweep measures a
change: run it once with ``PYTHONPATH`` pointing at each version.
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import io
import json
import os
import re
import shutil
import sys
import tempfile
import time
import warnings
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from PIL import Image

LITE = ["--preset", "deltar-lite", "--threads", "1"]
_BOX = re.compile(r"[│╭╮╰╯─]+")


@dataclass
class Case:
    """One malformed (or valid) input.

    Attributes:
        name: short identifier.
        run: CLI argument list (``{in}`` / ``{out}`` replaced by the input and the case's
            output folder) or a callable taking (inputs, out) for API cases.
        expect: ``"error"`` (must fail clearly) or ``"ok"`` (must succeed).
        needles: words the output must contain (case-insensitive).
        forbid: words the output must not contain.
        early: the problem can be found before building the network.
        setup: called with (inputs, out) before the case runs.
        no_output: paths (relative to out) that must not exist after a failure.
        group: the class of bad input the case belongs to (counted separately).
    """

    name: str
    run: list[str] | Callable
    expect: str = "error"
    needles: tuple[str, ...] = ()
    forbid: tuple[str, ...] = ()
    early: bool = True
    setup: Callable | None = None
    no_output: tuple[str, ...] = ()
    group: str = ""


@dataclass
class Outcome:
    verdict: str
    text: str
    seconds: float
    flags: list[str] = field(default_factory=list)


# ---------------------------------------------------------------------------- inputs
def _zone_dict(rng, grid=8, low=0.5, high=3.0):
    from deltar.io.zone_file import zone_frame_to_dict
    from deltar.sensor.zone_frame import ZoneFrame

    n = grid * grid
    frame = ZoneFrame(rng.uniform(low, high, n), np.full(n, 0.03), np.ones(n, bool))
    return zone_frame_to_dict(frame)


def build_inputs(root: Path) -> Path:
    """Write every input file the cases read into ``root/in``; return that folder."""
    from deltar.calibration.rig import RigCalibration
    from deltar.camera import CameraIntrinsics
    from deltar.sensor.geometry import SensorExtrinsics

    rng = np.random.default_rng(0)
    inp = root / "in"
    inp.mkdir(parents=True)
    rgb = rng.integers(0, 256, (48, 64, 3), dtype=np.uint8)
    Image.fromarray(rgb).save(inp / "img.png")
    Image.fromarray(rgb[..., 0]).save(inp / "grey.png")
    Image.fromarray(np.dstack([rgb, np.full((48, 64), 255, np.uint8)])).save(inp / "rgba.png")
    Image.fromarray(rng.integers(0, 4000, (48, 64)).astype(np.uint16)).save(inp / "depth16.png")
    Image.fromarray(rgb[:1, :1]).save(inp / "tiny.png")
    data = (inp / "img.png").read_bytes()
    (inp / "trunc.png").write_bytes(data[: len(data) // 2])
    (inp / "text.png").write_text("not an image\n")

    def zones(name, content):
        (inp / name).write_text(json.dumps(content))

    good = _zone_dict(rng)
    zones("z.json", good)
    zones("z4.json", _zone_dict(rng, grid=4))
    as_ints = dict(good, mean_m=[round(v) or 1 for v in good["mean_m"]],
                   valid=[1] * 64)
    zones("z_ints.json", as_ints)
    zones("z_strings.json", dict(good, mean_m=[str(v) for v in good["mean_m"]]))
    zones("z_bools.json", dict(good, mean_m=[True] * 64))
    zones("z_nan.json", dict(good, mean_m=[float("nan"), *good["mean_m"][1:]]))
    zones("z_negative.json", dict(good, mean_m=[-1.0, *good["mean_m"][1:]]))
    zones("z_count.json", dict(good, mean_m=good["mean_m"][:36], sigma_m=good["sigma_m"][:36],
                               valid=good["valid"][:36], zone_count=36))
    zones("z_invalid.json", dict(good, mean_m=[0.0] * 64, sigma_m=[0.0] * 64,
                                 valid=[False] * 64))
    zones("z_far.json", dict(good, mean_m=[1000000.0, *good["mean_m"][1:]]))
    zones("z_zero.json", dict(good, mean_m=[0.0] * 64))
    zones("z_ts.json", dict(good, timestamp_s="12.5"))
    zones("driver.json", {"distance_mm": [1500] * 64, "range_sigma_mm": [20] * 64,
                          "target_status": [5] * 60 + [255] * 4})
    zones("driver_codes.json", {"distance_mm": [-3] * 64, "range_sigma_mm": [0] * 64,
                                "target_status": [5] * 64})
    zones("driver_strings.json", {"distance_mm": ["1500"] * 64, "range_sigma_mm": [20] * 64,
                                  "target_status": [5] * 64})
    (inp / "z_corrupt.json").write_text("{not json")
    (inp / "z.txt").write_text(json.dumps(good))
    np.savez(inp / "z_strings.npz", mean_m=np.array(["1.0"] * 64), sigma_m=np.zeros(64),
             valid=np.ones(64, bool), schema_version=np.array(1))

    camera = CameraIntrinsics(60.0, 60.0, 31.5, 23.5, 64, 48)
    RigCalibration(camera, SensorExtrinsics()).save(inp / "calib.json")
    RigCalibration(CameraIntrinsics(500, 500, 319.5, 239.5, 640, 480),
                   SensorExtrinsics()).save(inp / "calib_640.json")
    (inp / "calib_corrupt.json").write_text("[1, 2")

    import torch

    (inp / "text.pt").write_text("e" * 200)
    (inp / "trunc.pt").write_bytes(b"PK\x03\x04" + bytes(100))
    torch.save({"weights": torch.zeros(2)}, inp / "foreign.pt")
    (inp / "outfile").write_text("a file, not a folder\n")

    folder = inp / "frames"
    folder.mkdir()
    for stem in ("f1", "f2"):
        shutil.copy(inp / "img.png", folder / f"{stem}.png")
        shutil.copy(inp / "z.json", folder / f"{stem}.json")
    shutil.copy(inp / "img.png", folder / "f3.png")
    (folder / "f3.json").write_text("{broken")
    (inp / "empty").mkdir()
    return inp


def build_recordings(inp: Path, cli) -> None:
    """A simulated wall recording, a ZJU-L5 set and a synthetic calibration recording."""
    from scipy.spatial.transform import Rotation

    from deltar.calibration.synthetic import synthetic_rig_frames, write_synthetic_recording
    from deltar.camera import CameraIntrinsics
    from deltar.sensor.geometry import SensorExtrinsics

    for args in (["record", str(inp / "rec"), "--simulate", "wall:1.5:4:48x64"],
                 ["simulate", "procedural:2:0:48x64", str(inp / "zju")]):
        result = cli(args)
        if result.exit_code != 0:
            raise RuntimeError(f"could not build inputs with {args}: {result.output}")
    lines = (inp / "rec" / "zones.jsonl").read_text().splitlines()
    shutil.copytree(inp / "rec", inp / "rec_corrupt")
    # A corrupt line in the middle (a truncated *last* line is an interrupted recording,
    # skipped with a warning by design).
    (inp / "rec_corrupt" / "zones.jsonl").write_text("\n".join([lines[0], "{oops",
                                                                 *lines[1:]]) + "\n")
    camera = CameraIntrinsics(150.0, 150.0, 79.5, 59.5, 160, 120)
    true = SensorExtrinsics(Rotation.from_euler("zyx", [92.0, -1.0, 1.5],
                                                degrees=True).as_matrix(),
                            np.array([0.03, 0.01, -0.01]))
    frames = synthetic_rig_frames(true, camera, frames_per_plane=2, mean_noise_m=0.01, seed=5)
    write_synthetic_recording(inp / "calrec", frames, camera)
    write_synthetic_recording(inp / "calrec_nodepth", frames, camera, with_depth=False)
    (inp / "vis.txt").write_text("a file\n")
    (inp / "plot.txt").write_text("a file\n")
    (inp / "metrics.json").write_text('{"keep": "me"}\n')


# ---------------------------------------------------------------------------- cases
def _predict(image="img.png", zones="z.json", *extra):
    return ["predict", "--image", f"{{in}}/{image}", "--zones", f"{{in}}/{zones}",
            "--out", "{out}", "--outputs", "npy", *LITE, *extra]


def _api(fn_name: str, *args, **kwargs):
    """An API case: estimator.predict(...) with the given arguments."""

    def run(inp: Path, out: Path):
        from deltar.data.rgbd_files import read_color
        from deltar.inference.loading import load_estimator
        from deltar.io.zone_file import load_zone_frame

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            estimator = _cached_estimator(load_estimator)
        image = read_color(inp / "img.png")
        frame = load_zone_frame(inp / "z.json")
        values = {"image": image, "frame": frame, "inp": inp}
        call_args = [a(values) if callable(a) else a for a in args]
        call_kwargs = {k: (v(values) if callable(v) else v) for k, v in kwargs.items()}
        return getattr(estimator, fn_name)(*call_args, **call_kwargs)

    return run


_ESTIMATOR = {}


def _cached_estimator(load_estimator):
    if "lite" not in _ESTIMATOR:
        _ESTIMATOR["lite"] = load_estimator("deltar-lite", kind="preset")
    return _ESTIMATOR["lite"]


def _zone_frame(**fields):
    def make(values):
        from deltar.sensor.zone_frame import ZoneFrame

        n = 64
        base = {"mean_m": np.full(n, 1.5), "sigma_m": np.full(n, 0.02),
                "valid": np.ones(n, bool)}
        base.update(fields)
        return ZoneFrame(**base)

    return make


def _api_call(fn: Callable):
    return lambda inp, out: fn(inp)


def _load_zone(name):
    def run(inp):
        from deltar.io.zone_file import load_zone_frame

        return load_zone_frame(inp / name)

    return run


def _driver_strings(inp):
    from deltar.sensor.zone_frame import ZoneFrame

    return ZoneFrame.from_driver(["1500"] * 64, [20] * 64, [5] * 64)


def _fov_scalar(inp):
    from deltar.inference.loading import load_estimator

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        return load_estimator("deltar-lite", kind="preset", fov_deg=60.0)


def _existing_outputs(inp, out):
    out.mkdir(parents=True, exist_ok=True)
    (out / "img_depth_m.npy").write_bytes(b"previous result")


def _existing_calib(inp, out):
    out.mkdir(parents=True, exist_ok=True)
    (out / "calib.json").write_text("{}")


def _api_no_zones(inp, out):
    """All zones invalid through the API: the result must say so (flag or warning)."""
    run = _api("predict", lambda v: v["image"],
               _zone_frame(mean_m=np.zeros(64), sigma_m=np.zeros(64),
                           valid=np.zeros(64, bool)))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        result = run(inp, out)
    said = [str(w.message) for w in caught if "valid zone" in str(w.message)]
    flagged = getattr(result, "image_only", None) is True
    if not flagged and not said:
        raise _Silent("an all-invalid frame gave a depth map with no flag and no warning")
    return "image-only estimate flagged: " + (said[0] if said else "image_only=True")


class _Silent(Exception):
    """Raised by a custom check: the call succeeded but should not have, silently."""


def _zju_copy(inp: Path, out: Path) -> list[Path]:
    """A copy of the ZJU-L5 set in the case's output folder; its frame files."""
    shutil.copytree(inp / "zju", out / "zju", dirs_exist_ok=True)
    return sorted((out / "zju").rglob("*.h5"))


def _zju_without_a_frame(inp: Path, out: Path) -> None:
    _zju_copy(inp, out)[-1].unlink()


def _zju_zones_away(inp: Path, out: Path) -> None:
    import h5py

    with h5py.File(_zju_copy(inp, out)[0], "r+") as f:  # the frame with valid zones
        f["fr"][...] = f["fr"][()] + 1e5


def cases() -> list[Case]:
    """Every case of the sweep."""
    from deltar.sensor.zone_frame import ZoneFrame  # noqa: F401  (import check)

    rec, zju, cal = "{in}/rec", "{in}/zju/data.json", "{in}/calrec"
    return [
        # ---- predict: files
        Case("predict-image-missing", _predict("nope.png"), needles=("nope.png", "not found")),
        Case("predict-zones-missing", _predict(zones="nope.json"),
             needles=("nope.json", "not found")),
        Case("predict-image-truncated", _predict("trunc.png"), needles=("trunc.png",)),
        Case("predict-image-text", _predict("text.png"), needles=("text.png",)),
        Case("predict-image-depth16", _predict("depth16.png"),
             needles=("depth16.png", "16-bit")),
        Case("predict-image-1px", _predict("tiny.png"), needles=("tiny.png", "small")),
        Case("predict-zones-strings", _predict(zones="z_strings.json"),
             needles=("z_strings.json", "mean_m", "number")),
        Case("predict-zones-bools", _predict(zones="z_bools.json"),
             needles=("z_bools.json", "mean_m", "number")),
        Case("predict-zones-timestamp-string", _predict(zones="z_ts.json"),
             needles=("z_ts.json", "timestamp_s")),
        Case("predict-zones-nan", _predict(zones="z_nan.json"),
             needles=("z_nan.json", "nan")),
        Case("predict-zones-negative", _predict(zones="z_negative.json"),
             needles=("z_negative.json", "negative")),
        Case("predict-zones-count", _predict(zones="z_count.json"),
             needles=("z_count.json", "zone count")),
        Case("predict-zones-corrupt", _predict(zones="z_corrupt.json"),
             needles=("z_corrupt.json", "json")),
        Case("predict-zones-suffix", _predict(zones="z.txt"), needles=("z.txt", ".json")),
        Case("predict-zones-npz-strings", _predict(zones="z_strings.npz"),
             needles=("z_strings.npz", "mean_m")),
        Case("predict-zones-all-invalid", _predict(zones="z_invalid.json"),
             needles=("z_invalid.json", "no valid zone")),
        Case("predict-driver-error-codes", _predict(zones="driver_codes.json"),
             needles=("driver_codes.json", "no valid zone")),
        Case("predict-driver-strings", _predict(zones="driver_strings.json"),
             needles=("driver_strings.json", "distance_mm")),
        Case("predict-zone-1e6-m", _predict(zones="z_far.json"),
             needles=("z_far.json", "range")),
        Case("predict-zones-all-0-m", _predict(zones="z_zero.json"),
             needles=("z_zero.json", "range")),
        # ---- predict: options
        Case("predict-threads-0", [*_predict(), "--threads", "0"], needles=("--threads",)),
        Case("predict-threads-negative", [*_predict(), "--threads", "-1"],
             needles=("--threads",)),
        Case("predict-device-cuda", [*_predict(), "--device", "cuda"],
             needles=("--device", "cuda")),
        Case("predict-device-bogus", [*_predict(), "--device", "bogus"],
             needles=("--device", "bogus")),
        Case("predict-precision-bogus", [*_predict(), "--precision", "float64"],
             needles=("precision", "float64")),
        Case("predict-size-text", [*_predict(), "--size", "big"], needles=("size", "big")),
        Case("predict-size-not-32", [*_predict(), "--size", "100x100"],
             needles=("size", "32")),
        Case("predict-outputs-bogus", [*_predict(), "--outputs", "jpeg"],
             needles=("--outputs", "jpeg")),
        Case("predict-missing-zones-option", ["predict", "--image", "{in}/img.png", "--out",
                                              "{out}", *LITE], needles=("--zones",)),
        Case("predict-two-models", [*_predict(), "--checkpoint", "default"],
             needles=("only one of",)),
        Case("predict-preset-bogus", ["predict", "--image", "{in}/img.png", "--zones",
                                      "{in}/z.json", "--out", "{out}", "--preset", "bogus"],
             needles=("bogus",), early=False),
        Case("predict-calib-missing", [*_predict(), "--calib", "{in}/nocalib.json"],
             needles=("nocalib.json", "not found")),
        Case("predict-calib-corrupt", [*_predict(), "--calib", "{in}/calib_corrupt.json"],
             needles=("calib_corrupt.json", "json")),
        Case("predict-calib-resolution", [*_predict(), "--calib", "{in}/calib_640.json"],
             needles=("calib", "resolution")),
        Case("predict-out-is-file", ["predict", "--image", "{in}/img.png", "--zones",
                                     "{in}/z.json", "--out", "{in}/outfile", *LITE],
             needles=("outfile", "folder")),
        Case("predict-out-under-file", ["predict", "--image", "{in}/img.png", "--zones",
                                        "{in}/z.json", "--out", "{in}/outfile/sub", *LITE],
             needles=("outfile",)),
        Case("predict-existing-output", _predict(), needles=("img_depth_m.npy", "overwrite"),
             setup=_existing_outputs),
        Case("predict-checkpoint-text", ["predict", "--image", "{in}/img.png", "--zones",
                                         "{in}/z.json", "--out", "{out}", "--checkpoint",
                                         "{in}/text.pt"],
             needles=("text.pt",), forbid=("weights_only", ": 101"), early=False),
        Case("predict-checkpoint-truncated", ["predict", "--image", "{in}/img.png", "--zones",
                                              "{in}/z.json", "--out", "{out}",
                                              "--checkpoint", "{in}/trunc.pt"],
             needles=("trunc.pt",), forbid=("weights_only",), early=False),
        Case("predict-checkpoint-foreign", ["predict", "--image", "{in}/img.png", "--zones",
                                            "{in}/z.json", "--out", "{out}", "--checkpoint",
                                            "{in}/foreign.pt"],
             needles=("foreign.pt", "not a deltar checkpoint"), early=False),
        Case("predict-checkpoint-missing", ["predict", "--image", "{in}/img.png", "--zones",
                                            "{in}/z.json", "--out", "{out}", "--checkpoint",
                                            "{in}/none.pt"], needles=("none.pt",)),
        Case("predict-official-missing", ["predict", "--image", "{in}/img.png", "--zones",
                                          "{in}/z.json", "--out", "{out}", "--official",
                                          "{in}/nyu.pt"], needles=("nyu.pt", "not found")),
        Case("predict-onnx-missing", ["predict", "--image", "{in}/img.png", "--zones",
                                      "{in}/z.json", "--out", "{out}", "--onnx",
                                      "{in}/m.onnx"], needles=("m.onnx",)),
        Case("predict-folder-missing", ["predict", "--images", "{in}/nofolder", "--zones-dir",
                                        "{in}/frames", "--out", "{out}", *LITE],
             needles=("nofolder", "not found")),
        Case("predict-folder-no-pairs", ["predict", "--images", "{in}/empty", "--zones-dir",
                                         "{in}/frames", "--out", "{out}", *LITE],
             needles=("empty",)),
        Case("predict-folder-bad-frame", ["predict", "--images", "{in}/frames", "--zones-dir",
                                          "{in}/frames", "--out", "{out}", *LITE],
             needles=("f3.json",), early=False),
        # ---- predict: valid inputs
        Case("predict-valid", _predict(), expect="ok", needles=("no --calib", "nominal")),
        Case("predict-valid-4x4", _predict(zones="z4.json"), expect="ok"),
        Case("predict-valid-driver-dump", _predict(zones="driver.json"), expect="ok"),
        Case("predict-valid-int-values", _predict(zones="z_ints.json"), expect="ok"),
        Case("predict-valid-grey-image", _predict("grey.png"), expect="ok"),
        Case("predict-valid-rgba-image", _predict("rgba.png"), expect="ok"),
        Case("predict-valid-calib", [*_predict(), "--calib", "{in}/calib.json"], expect="ok",
             forbid=("no --calib",)),
        # ---- Python API
        Case("api-image-2d", _api("predict", np.zeros((48, 64), np.uint8),
                                  lambda v: v["frame"]), needles=("(H, W, 3)", "(48, 64)")),
        Case("api-image-tensor", _api("predict", lambda v: __import__("torch").zeros(48, 64, 3),
                                      lambda v: v["frame"]), needles=("(H, W, 3)", "tensor")),
        Case("api-image-dict", _api("predict", {"rgb": 1}, lambda v: v["frame"]),
             needles=("(H, W, 3)", "dict")),
        Case("api-image-path", _api("predict", lambda v: str(v["inp"] / "img.png"),
                                    lambda v: v["frame"]), needles=("(H, W, 3)", "str")),
        Case("api-image-float", _api("predict", np.zeros((48, 64, 3), np.float32),
                                     lambda v: v["frame"]), needles=("uint8",)),
        Case("api-calibration-dict", _api("predict", lambda v: v["image"],
                                          lambda v: v["frame"], calibration={"fx": 1}),
             needles=("calibration", "RigCalibration")),
        Case("api-zone-frame-dict", _api("predict", lambda v: v["image"], {"mean_m": [1]}),
             needles=("zone_frame", "ZoneFrame")),
        Case("api-zone-frame-none", _api("predict", lambda v: v["image"], None),
             needles=("ZoneFrame",)),
        Case("api-zone-1e6-m", _api("predict", lambda v: v["image"],
                                    _zone_frame(mean_m=np.r_[1e6, np.full(63, 1.5)])),
             needles=("range",)),
        Case("api-zones-all-0-m", _api("predict", lambda v: v["image"],
                                       _zone_frame(mean_m=np.zeros(64))), needles=("range",)),
        Case("api-no-valid-zone", _api_no_zones, expect="ok"),
        Case("api-driver-strings", _api_call(_driver_strings),
             needles=("distance_mm", "number")),
        Case("api-fov-deg-scalar", _api_call(_fov_scalar), needles=("fov_deg", "two angles")),
        Case("api-load-npz-strings", _api_call(_load_zone("z_strings.npz")),
             needles=("z_strings.npz", "mean_m")),
        Case("api-valid-batch", _api("predict", lambda v: [v["image"], v["image"]],
                                     lambda v: [v["frame"], v["frame"]]), expect="ok"),
        # ---- replay
        Case("replay-missing", ["replay", "{in}/norec", "--out", "{out}", *LITE],
             needles=("norec", "not found")),
        Case("replay-every-0", ["replay", rec, "--out", "{out}", "--every", "0", *LITE],
             needles=("--every",)),
        Case("replay-limit-0", ["replay", rec, "--out", "{out}", "--limit", "0", *LITE],
             needles=("--limit",)),
        Case("replay-tolerance-negative", ["replay", rec, "--out", "{out}", "--tolerance",
                                           "-1", *LITE], needles=("--tolerance",)),
        Case("replay-show-no-display", ["replay", rec, "--show", *LITE],
             needles=("--show",)),
        Case("replay-no-out", ["replay", rec, *LITE], needles=("--out",)),
        Case("replay-out-inside", ["replay", rec, "--out", f"{rec}/o", *LITE],
             needles=("inside the input",)),
        Case("replay-corrupt-zones", ["replay", "{in}/rec_corrupt", "--out", "{out}", *LITE],
             needles=("zones.jsonl",)),
        Case("replay-valid", ["replay", rec, "--out", "{out}", *LITE], expect="ok"),
        # ---- record
        Case("record-grid-3", ["record", "{out}/r", "--simulate", "wall:1.5:2:48x64",
                               "--grid", "3"], needles=("--grid",)),
        Case("record-simulate-bogus", ["record", "{out}/r", "--simulate", "bogus"],
             needles=("bogus",)),
        Case("record-wall-bad", ["record", "{out}/r", "--simulate", "wall:abc"],
             needles=("wall",)),
        Case("record-frames-0", ["record", "{out}/r", "--simulate", "wall:1.5:2:48x64",
                                 "--frames", "0"], needles=("frames",)),
        Case("record-sensor-hz-0", ["record", "{out}/r", "--simulate", "wall:1.5:2:48x64",
                                    "--sensor-hz", "0"], needles=("--sensor-hz",)),
        Case("record-hardware-no-calib", ["record", "{out}/r"], needles=("--calib",)),
        Case("record-valid", ["record", "{out}/r", "--simulate", "wall:1.5:2:48x64"],
             expect="ok"),
        # ---- simulate
        Case("simulate-1x1", ["simulate", "procedural:1:0:1x1", "{out}/s"],
             needles=("1x1",)),
        Case("simulate-src-missing", ["simulate", "{in}/nosrc", "{out}/s"],
             needles=("nosrc", "not found")),
        Case("simulate-grid-3", ["simulate", "procedural:1:0:48x64", "{out}/s", "--grid", "3"],
             needles=("--grid",)),
        Case("simulate-out-not-empty", ["simulate", "procedural:1:0:48x64", "{in}/frames"],
             needles=("frames", "empty")),
        Case("simulate-intrinsics-bad", ["simulate", "procedural:1:0:48x64", "{out}/s",
                                         "--intrinsics", "1,2"], needles=("--intrinsics",)),
        Case("simulate-valid", ["simulate", "procedural:1:0:48x64", "{out}/s"], expect="ok"),
        # ---- demo
        Case("demo-size-1x1", ["demo", "{out}/d", "--frames", "1", "--size", "1x1"],
             needles=("--size",)),
        Case("demo-size-text", ["demo", "{out}/d", "--frames", "1", "--size", "big"],
             needles=("--size",)),
        Case("demo-into-file", ["demo", "{in}/outfile", "--frames", "1", "--size", "48x64"],
             needles=("outfile",)),
        # ---- evaluate
        Case("evaluate-json-exists", ["evaluate", "--data", zju, "--method", "nearest",
                                      "--json", "{in}/metrics.json"],
             needles=("metrics.json", "overwrite")),
        Case("evaluate-save-vis-file", ["evaluate", "--data", zju, "--method", "nearest",
                                        "--save-vis", "{in}/vis.txt"], needles=("vis.txt",)),
        Case("evaluate-data-missing", ["evaluate", "--data", "{in}/none.json", "--method",
                                       "nearest"], needles=("none.json", "not found")),
        Case("evaluate-method-bogus", ["evaluate", "--data", zju, "--method", "bogus"],
             needles=("bogus",)),
        Case("evaluate-split-bogus", ["evaluate", "--data", zju, "--method", "nearest",
                                      "--split", "nope"], needles=("nope",)),
        Case("evaluate-checkpoint-text", ["evaluate", "--data", zju, "--checkpoint",
                                          "{in}/text.pt"], needles=("text.pt",),
             forbid=("weights_only", ": 101")),
        Case("evaluate-limit-0", ["evaluate", "--data", zju, "--method", "nearest",
                                  "--limit", "0"], needles=("--limit",)),
        Case("evaluate-valid", ["evaluate", "--data", zju, "--method", "nearest", "--json",
                                "{out}/m.json"], expect="ok"),
        Case("evaluate-json-on-onnx-method", ["evaluate", "--data", zju, "--method",
                                              "onnx:{out}/v.onnx", "--json", "{out}/v.onnx",
                                              "--overwrite"],
             needles=("v.onnx", "is the input"),
             setup=lambda inp, out: (out / "v.onnx").write_bytes(b"model")),
        Case("evaluate-frame-missing", ["evaluate", "--data", "{out}/zju/data.json",
                                        "--method", "nearest"],
             needles=("--data", "frame file not found", ".h5"), setup=_zju_without_a_frame),
        Case("evaluate-zones-outside-image", ["evaluate", "--data", "{out}/zju/data.json",
                                              "--method", "nearest"],
             needles=(".h5", "fall outside the"), setup=_zju_zones_away),
        # ---- calibrate
        Case("calibrate-roll-nan", ["calibrate", cal, "--out", "{out}/c.json",
                                    "--nominal-roll-deg", "nan"],
             needles=("--nominal-roll-deg",)),
        Case("calibrate-fov-zero", ["calibrate", cal, "--out", "{out}/c.json", "--fov", "0,0"],
             needles=("--fov",)),
        Case("calibrate-no-depth", ["calibrate", "{in}/calrec_nodepth", "--out",
                                    "{out}/c.json"], needles=("depth",)),
        Case("calibrate-roll-wrong-sign", ["calibrate", cal, "--out", "{out}/c.json",
                                           "--nominal-roll-deg", "-90"],
             needles=("--nominal-roll-deg",)),
        Case("calibrate-plot-file", ["calibrate", cal, "--out", "{out}/c.json", "--plot",
                                     "{in}/plot.txt"], needles=("plot.txt",),
             no_output=("c.json",)),
        Case("calibrate-out-exists", ["calibrate", cal, "--out", "{out}/calib.json"],
             needles=("calib.json", "exists"), setup=_existing_calib),
        Case("calibrate-translation-bad", ["calibrate", cal, "--out", "{out}/c.json",
                                           "--nominal-translation", "1,2"],
             needles=("--nominal-translation",)),
        Case("calibrate-missing", ["calibrate", "{in}/norec", "--out", "{out}/c.json"],
             needles=("norec", "not found")),
        Case("calibrate-slam-half", ["calibrate", cal, "--out", "{out}/c.json",
                                     "--slam-cloud", "{in}/x.ply"], needles=("--slam",)),
        Case("calibrate-valid", ["calibrate", cal, "--out", "{out}/c.json"], expect="ok"),
        # ---- export, wall-test, bench, train
        Case("export-format-bogus", ["export", "--preset", "deltar-lite", "--out",
                                     "{out}/m.onnx", "--format", "tflite"],
             needles=("--format",)),
        Case("export-size-bad", ["export", "--preset", "deltar-lite", "--out", "{out}/m.onnx",
                                 "--size", "big"], needles=("size",)),
        Case("export-layout-missing", ["export", "--preset", "deltar-lite", "--out",
                                       "{out}/m.onnx", "--layout-from", "{in}/nocal.json"],
             needles=("nocal.json",)),
        Case("export-int8-calibration-not-rgbd", ["export", "--preset", "deltar-lite",
                                                  "--out", "{out}/m.onnx", "--size", "64x96",
                                                  "--int8", "--calibration", "{in}/empty"],
             needles=("--calibration", "empty")),
        # The other size's name follows the model's design size: found once it is built.
        Case("export-size-file-is-folder", ["export", "--preset", "deltar-lite", "--out",
                                            "{out}/m.onnx", "--size", "240x320,480x480"],
             needles=("m.544x544.onnx", "folder"), early=False,
             no_output=("m.onnx", "m.onnx.data"),
             setup=lambda inp, out: (out / "m.544x544.onnx").mkdir(exist_ok=True)),
        Case("wall-test-missing", ["wall-test", "{in}/norec", "--out", "{out}", *LITE],
             needles=("norec",)),
        Case("wall-test-every-0", ["wall-test", rec, "--out", "{out}", "--every", "0", *LITE],
             needles=("--every",)),
        Case("bench-size-bad", ["bench", "--size", "100x100"], needles=("--size",)),
        Case("train-config-missing", ["train", "--config", "{in}/none.yaml"],
             needles=("none.yaml",)),
    ]


# ---------------------------------------------------------------------------- round 2
def build_round2_inputs(inp: Path) -> None:
    """Inputs of :func:`round2_cases`: unreadable files, odd fields, impossible values."""
    import h5py

    from deltar.calibration.rig import RigCalibration
    from deltar.camera import CameraIntrinsics
    from deltar.sensor.geometry import SensorExtrinsics

    deep = "[" * 50_000 + "]" * 50_000
    good = json.loads((inp / "z.json").read_text())
    calib = json.loads((inp / "calib.json").read_text())

    def write(name, content):
        (inp / name).write_text(content if isinstance(content, str) else json.dumps(content))

    def calib_with(name, **changes):
        data = json.loads(json.dumps(calib))
        for key, value in changes.items():
            section, _, field = key.partition("__")
            if field:
                data[section][field] = value
            else:
                data[section] = value
        write(name, data)

    npz = (inp / "z_strings.npz").read_bytes()
    (inp / "r2_trunc10.npz").write_bytes(npz[:10])
    write("r2_inf.json", json.dumps(dict(good, mean_m=[1.5] * 63 + [0])).replace(
        "0]", "1e400]", 1))
    write("r2_digits.json", '{"mean_m": [' + "1" * 5000 + "]}")
    (inp / "r2_utf16.json").write_bytes(json.dumps(good).encode("utf-16"))
    write("r2_deep_calib.json", deep)
    calib_with("r2_grid_string.json", grid="8")
    calib_with("r2_fov_null.json", fov_deg=None)
    calib_with("r2_rot_2x2.json", extrinsics__rotation=[[1, 0], [0, 1]])
    calib_with("r2_pp_negative.json", intrinsics__cy=-100.0)
    calib_with("r2_translation_5m.json", extrinsics__translation_m=[5.0, 0.0, 0.0])
    calib_with("r2_zones_away.json", fov_deg=[1.0, 1.0],
               extrinsics__rotation=[[1, 0, 0], [0, 0.5, -0.8660254037844386],
                                     [0, 0.8660254037844386, 0.5]])
    write("r2_sigma_5m.json", dict(good, sigma_m=[5.0] + [0.03] * 63))
    write("r2_hist_zero.json", dict(good, hist_edges_m=[0.0, 2.0, 4.0],
                                    hist_counts=[[0, 0]] * 2 + [[3, 1]] * 62))
    write("r2_valid_255.json", dict(good, status=[5] * 63 + [255]))
    write("r2_status_frac.json", dict(good, status=[5.5] * 64))
    write("r2_status_256.json", dict(good, status=[256] * 64))
    write("r2_driver_sigma.json", {"distance_mm": [1500] * 64,
                                   "range_sigma_mm": [10_000_000] + [20] * 63,
                                   "target_status": [5] * 64})
    write("r2_driver_status_frac.json", {"distance_mm": [1500] * 64, "range_sigma_mm": [20] * 64,
                                         "target_status": [5.5] * 64})
    write("r2_deep.yaml", "a: " + "[" * 50_000 + "]" * 50_000 + "\n")
    (inp / "r2_binary.yaml").write_bytes(b"\xff\xfe\x00bad")
    (inp / "r2_folder.pt").mkdir()
    # Recordings with a broken meta.json / zones.jsonl, or nothing to replay.
    for name, edit in (("r2_rec_deep_meta", lambda r: (r / "meta.json").write_text(deep)),
                       ("r2_rec_deep_line", lambda r: (r / "zones.jsonl").write_text(
                           (r / "zones.jsonl").read_text() + deep + "\n{}\n")),
                       ("r2_rec_inf_width", lambda r: (r / "meta.json").write_text(
                           (r / "meta.json").read_text().replace('"width": 64',
                                                                 '"width": 1e400'))),
                       ("r2_rec_blank", lambda r: (r / "zones.jsonl").write_text("\n \n"))):
        shutil.copytree(inp / "rec", inp / name)
        edit(inp / name)
    # Sets with an impossible frame, a deep index, a frame whose rgb is a scalar.
    for name in ("r2_zju_far", "r2_zju_sigma", "r2_zju_scalar_rgb"):
        shutil.copytree(inp / "zju", inp / name)
    frame = sorted((inp / "r2_zju_far").rglob("*.h5"))[0]
    with h5py.File(frame, "r+") as f:
        zones = f["hist_data"][()]
        zones[int(np.flatnonzero(f["mask"][()].reshape(-1))[0]), 0] = 50.0
        f["hist_data"][...] = zones
    frame = sorted((inp / "r2_zju_sigma").rglob("*.h5"))[0]
    with h5py.File(frame, "r+") as f:
        zones = f["hist_data"][()]
        zones[int(np.flatnonzero(f["mask"][()].reshape(-1))[0]), 1] = 1e6
        f["hist_data"][...] = zones
    frame = sorted((inp / "r2_zju_scalar_rgb").rglob("*.h5"))[0]
    with h5py.File(frame, "r+") as f:
        del f["rgb"]
        f["rgb"] = np.uint8(3)
    write("r2_deep_index.json", deep)
    # Two inputs with one stem; a folder whose zone files share a stem.
    for name, files in (("r2_same_stem", ("a.png", "a.jpg")), ("r2_same_zone_stem", ())):
        folder = inp / name
        folder.mkdir()
        shutil.copy(inp / "img.png", folder / "a.png")
        for extra in files[1:]:
            shutil.copy(inp / "img.png", folder / extra)
        shutil.copy(inp / "z.json", folder / "a.json")
    np.savez(inp / "r2_same_zone_stem" / "a.npz", x=np.zeros(1))
    (inp / "r2_model.pt").write_bytes(b"weights")
    # Second batch: more readers and more odd values.
    text_jpg = inp / "r2b_text.jpg"
    text_jpg.write_text("not a jpeg\n")
    png = bytearray((inp / "img.png").read_bytes())
    png[60:80] = bytes(20)  # damaged chunk data and CRC
    (inp / "r2b_badcrc.png").write_bytes(bytes(png))
    np.savez(inp / "r2b_object.npz", mean_m=np.array([{"a": 1}] * 64, dtype=object),
             sigma_m=np.zeros(64), valid=np.ones(64, bool), schema_version=np.array(1))
    import zipfile

    with zipfile.ZipFile(inp / "r2b_not_npy.npz", "w") as archive:
        archive.writestr("mean_m.npy", b"not an array")
    write("r2b_list.json", [1, 2, 3])
    write("r2b_null_mean.json", dict(good, mean_m=None))
    write("r2b_ragged_hist.json", dict(good, hist_edges_m=[0.0, 2.0, 4.0],
                                       hist_counts=[[1, 1]] * 63 + [[1]]))
    write("r2b_calib_inf_fx.json", json.dumps(calib).replace('"fx": 60.0', '"fx": 1e400'))
    calib_with("r2b_calib_distortion_text.json", distortion="abc")
    calib_with("r2b_calib_residual_null.json", residuals={"a": None})
    shutil.copytree(inp / "rec", inp / "r2b_rec_grid_frac")
    meta = inp / "r2b_rec_grid_frac" / "meta.json"
    meta.write_text(meta.read_text().replace('"grid": 8', '"grid": 8.5'))
    shutil.copytree(inp / "rec", inp / "r2b_rec_number_line")
    lines = (inp / "rec" / "zones.jsonl").read_text().splitlines()
    (inp / "r2b_rec_number_line" / "zones.jsonl").write_text(
        "\n".join([lines[0], "5", *lines[1:]]) + "\n")
    RigCalibration(CameraIntrinsics(60.0, 60.0, 31.5, 23.5, 64, 48), SensorExtrinsics(),
                   grid=4).save(inp / "r2c_calib_grid4.json")
    write("r2c_zone_count_text.json", dict(good, zone_count="64"))
    write("r2d_hist_shape.json", dict(good, hist_edges_m=[0, 1, 2, 3], hist_counts=[[1, 1]] * 64))
    write("r2d_valid_2.json", dict(good, valid=[1] * 63 + [2]))
    np.savez(inp / "r2d_valid_half.npz", mean_m=np.full(64, 1.5), sigma_m=np.full(64, 0.02),
             valid=np.full(64, 0.5), schema_version=np.array(1))
    write("r2d_fake.mat", "not a MATLAB file\n")
    write("r2c_driver_mixed.json", {"distance_mm": [1500] * 16, "range_sigma_mm": [20] * 64,
                                    "target_status": [5] * 64})
    (inp / "r2b_traj_utf16.txt").write_bytes("0 0 0 0 0 0 0 1\n".encode("utf-16"))
    (inp / "r2b_garbage.ply").write_bytes(b"ply\nformat binary_little_endian 1.0\n"
                                          b"element vertex 1000\nproperty float x\n"
                                          b"property float y\nproperty float z\n"
                                          b"end_header\n" + bytes(12))
    (inp / "r2_zones_link.jsonl").symlink_to(inp / "rec" / "zones.jsonl")
    os.link(inp / "rec" / "meta.json", inp / "r2_meta_hardlink.json")


def _r2_api(make):
    """An API case: ``make(inp)`` must raise (or return) by itself."""
    return lambda inp, out: make(inp)


def _r2_zone_frame(**fields):
    def make(inp):
        from deltar.sensor.zone_frame import ZoneFrame

        base = {"mean_m": np.full(64, 1.5), "sigma_m": np.full(64, 0.02),
                "valid": np.ones(64, bool), **fields}
        return ZoneFrame(**base)

    return _r2_api(make)


def _r2_rig(**changes):
    def make(inp):
        from deltar.calibration.rig import RigCalibration
        from deltar.camera import CameraIntrinsics
        from deltar.sensor.geometry import SensorExtrinsics

        intr = {"fx": 60.0, "fy": 60.0, "cx": 31.5, "cy": 23.5, "width": 64, "height": 48}
        intr.update({k: v for k, v in changes.items() if k in intr})
        return RigCalibration(CameraIntrinsics(**intr),
                              SensorExtrinsics(np.eye(3), changes.get("t", np.zeros(3))))

    return _r2_api(make)


def _r2_threads(inp):
    from deltar.inference.loading import load_estimator

    return load_estimator("deltar-lite", kind="preset", threads=10**6)


def round2_cases() -> list[Case]:
    """New cases of issue #24's classes, none of them in the tests or the first list."""
    rec, zju, cal = "{in}/rec", "{in}/zju/data.json", "{in}/calrec"
    lite_predict = _predict
    tiny = "tiny_test.yaml"
    config = str(Path(__file__).resolve().parents[1] / "configs" / tiny)

    def grouped(group):
        return lambda name, *args, **kw: Case(name, *args, group=group, **kw)

    read, path, apart, machine, physical, other = (grouped(group) for group in (
        "reading", "paths", "output-input", "machine", "physical", "stems-empty-steps"))

    return [
        read("r2-zones-npz-10-bytes", lite_predict(zones="r2_trunc10.npz"),
             needles=("r2_trunc10.npz", "corrupt or truncated")),
        read("r2-zones-1e400", lite_predict(zones="r2_inf.json"),
             needles=("r2_inf.json", "infinite")),
        read("r2-zones-5000-digits", lite_predict(zones="r2_digits.json"),
             needles=("r2_digits.json",)),
        read("r2-zones-utf16", lite_predict(zones="r2_utf16.json"),
             needles=("r2_utf16.json", "utf-8")),
        read("r2-calib-deep", [*lite_predict(), "--calib", "{in}/r2_deep_calib.json"],
             needles=("r2_deep_calib.json", "nested too deeply")),
        read("r2-calib-grid-string", [*lite_predict(), "--calib", "{in}/r2_grid_string.json"],
             needles=("r2_grid_string.json", "grid must be a number")),
        read("r2-calib-fov-null", [*lite_predict(), "--calib", "{in}/r2_fov_null.json"],
             needles=("r2_fov_null.json", "invalid calibration")),
        read("r2-calib-rotation-2x2", [*lite_predict(), "--calib", "{in}/r2_rot_2x2.json"],
             needles=("r2_rot_2x2.json", "rotation")),
        read("r2-replay-meta-deep", ["replay", "{in}/r2_rec_deep_meta", "--out", "{out}",
                                     *LITE], needles=("meta.json", "nested too deeply")),
        read("r2-replay-zone-line-deep", ["replay", "{in}/r2_rec_deep_line", "--out", "{out}",
                                          *LITE], needles=("zones.jsonl", "nested too deeply")),
        read("r2-replay-meta-inf-width", ["replay", "{in}/r2_rec_inf_width", "--out", "{out}",
                                          *LITE], needles=("meta.json", "width")),
        read("r2-evaluate-index-deep", ["evaluate", "--data", "{in}/r2_deep_index.json",
                                        "--method", "nearest"],
             needles=("r2_deep_index.json", "nested too deeply")),
        read("r2-evaluate-scalar-rgb", ["evaluate", "--data", "{in}/r2_zju_scalar_rgb/data.json",
                                        "--method", "nearest"], needles=(".h5",)),
        read("r2-train-config-deep", ["train", "--config", "{in}/r2_deep.yaml"],
             needles=("r2_deep.yaml",)),
        read("r2-train-config-binary", ["train", "--config", "{in}/r2_binary.yaml"],
             needles=("r2_binary.yaml",)),
        read("r2-api-load-zone-npz-truncated",
             _r2_api(lambda inp: __import__("deltar.io.zone_file", fromlist=["x"])
                     .load_zone_frame(inp / "r2_trunc10.npz")),
             needles=("r2_trunc10.npz", "corrupt or truncated")),
        path("r2-zones-a-folder", lite_predict(zones="frames"),
             needles=("frames", "is a folder, not a file")),
        path("r2-calib-dev-zero", [*lite_predict(), "--calib", "/dev/zero"],
             needles=("/dev/zero", "not a regular file")),
        path("r2-replay-recording-a-file", ["replay", "{in}/outfile", "--out", "{out}", *LITE],
             needles=("outfile", "is a file, not a folder")),
        path("r2-calibrate-slam-dev-null", ["calibrate", cal, "--out", "{out}/c.json",
                                            "--slam-cloud", "/dev/null", "--slam-trajectory",
                                            "/dev/null"], needles=("/dev/null",)),
        path("r2-evaluate-data-dev-null", ["evaluate", "--data", "/dev/null", "--method",
                                           "nearest"], needles=("/dev/null", "regular file")),
        path("r2-train-config-folder", ["train", "--config", "{in}/empty"],
             needles=("empty", "folder")),
        path("r2-checkpoint-a-folder", [*lite_predict()[:-4], "--checkpoint",
                                        "{in}/r2_folder.pt"], needles=("r2_folder.pt",
                                                                       "folder")),
        apart("r2-calibrate-out-symlink-to-zones", ["calibrate", rec, "--out",
                                                    "{in}/r2_zones_link.jsonl", "--overwrite"],
              needles=("r2_zones_link.jsonl", "input")),
        apart("r2-calibrate-out-hardlink-meta", ["calibrate", rec, "--out",
                                                 "{in}/r2_meta_hardlink.json", "--overwrite"],
              needles=("r2_meta_hardlink.json", "input")),
        apart("r2-export-out-is-layout", ["export", "--preset", "deltar-lite", "--layout-from",
                                          "{in}/calib.json", "--out", "{in}/calib.json",
                                          "--overwrite"], needles=("calib.json", "input")),
        apart("r2-fit-uncertainty-out-is-data", ["fit-uncertainty", "{in}/r2_model.pt",
                                                 "--data", zju, "--out", zju, "--overwrite"],
              needles=("data.json", "input")),
        apart("r2-wall-test-out-is-recording", ["wall-test", rec, "--out", rec, *LITE],
              needles=("--out", "input")),
        apart("r2-replay-out-in-color", ["replay", rec, "--out", f"{rec}/color", *LITE],
              needles=("--out", "input")),
        apart("r2-map-out-inside", ["map", rec, "--out", f"{rec}/map", *LITE],
              needles=("--out", "input")),
        machine("r2-replay-threads-huge", ["replay", rec, "--out", "{out}", "--preset",
                                           "deltar-lite", "--threads", "100000"],
                needles=("--threads", "cpus")),
        machine("r2-wall-test-threads-huge", ["wall-test", rec, "--out", "{out}", "--preset",
                                              "deltar-lite", "--threads", "99999"],
                needles=("--threads",)),
        machine("r2-bench-batch-huge", ["bench", "--preset", "deltar-lite", "--batch",
                                        "1000000"], needles=("--batch", "memory")),
        machine("r2-check-official-threads-0", ["check-official", "{in}/text.pt", "--threads",
                                                "0"], needles=("--threads",)),
        machine("r2-train-devices-1000", ["train", "--config", config, "--override",
                                          "trainer.devices=1000", "--run-dir", "{out}/run"],
                needles=("trainer.devices", "this machine")),
        machine("r2-train-num-threads-huge", ["train", "--config", config, "--override",
                                              "trainer.num_threads=1000000", "--run-dir",
                                              "{out}/run"], needles=("trainer.num_threads",)),
        machine("r2-api-threads-huge", _r2_api(_r2_threads), needles=("threads",)),
        physical("r2-zones-sigma-5m", lite_predict(zones="r2_sigma_5m.json"),
                 needles=("r2_sigma_5m.json", "sigma")),
        physical("r2-zones-hist-zero", lite_predict(zones="r2_hist_zero.json"),
                 needles=("r2_hist_zero.json", "all-zero histogram")),
        physical("r2-zones-valid-255", lite_predict(zones="r2_valid_255.json"),
                 needles=("r2_valid_255.json", "255")),
        physical("r2-zones-status-5.5", lite_predict(zones="r2_status_frac.json"),
                 needles=("r2_status_frac.json", "status")),
        physical("r2-zones-status-256", lite_predict(zones="r2_status_256.json"),
                 needles=("r2_status_256.json", "status")),
        physical("r2-driver-status-5.5", lite_predict(zones="r2_driver_status_frac.json"),
                 needles=("r2_driver_status_frac.json", "target_status")),
        physical("r2-driver-sigma-10km", lite_predict(zones="r2_driver_sigma.json"),
                 expect="ok"),
        physical("r2-calib-principal-point", [*lite_predict(), "--calib",
                                              "{in}/r2_pp_negative.json"],
                 needles=("r2_pp_negative.json", "principal point")),
        physical("r2-calib-translation-5m", [*lite_predict(), "--calib",
                                             "{in}/r2_translation_5m.json"],
                 needles=("r2_translation_5m.json", "from the camera")),
        physical("r2-calib-zones-away", [*lite_predict(), "--calib",
                                         "{in}/r2_zones_away.json"],
                 needles=("r2_zones_away.json", "outside the")),
        physical("r2-evaluate-zone-50m", ["evaluate", "--data",
                                          "{in}/r2_zju_far/data.json", "--method", "nearest"],
                 needles=("range",)),
        physical("r2-evaluate-sigma-1e6", ["evaluate", "--data",
                                           "{in}/r2_zju_sigma/data.json", "--method",
                                           "nearest"], needles=("sigma",)),
        physical("r2-calibrate-nominal-20m", ["calibrate", cal, "--out", "{out}/c.json",
                                              "--nominal-translation", "20,0,0"],
                 needles=("--nominal-translation",)),
        physical("r2-api-zone-strings", _r2_zone_frame(mean_m=["1.5"] * 64),
                 needles=("mean_m", "numbers")),
        physical("r2-api-valid-strings", _r2_zone_frame(valid=["no"] * 64),
                 needles=("valid", "booleans")),
        physical("r2-api-status-fraction", _r2_zone_frame(status=np.full(64, 9.9)),
                 needles=("status", "integer")),
        physical("r2-api-intrinsics-string", _r2_rig(fx="60"), needles=("fx", "number")),
        physical("r2-api-rig-translation-5m", _r2_rig(t=np.array([0.0, 0.0, 5.0])),
                 needles=("from the camera",)),
        physical("r2-api-rig-width-fraction", _r2_rig(width=64.5), needles=("width",)),
        read("r2b-image-text-as-jpg", lite_predict("r2b_text.jpg"),
             needles=("r2b_text.jpg", "decode")),
        read("r2b-image-bad-crc", lite_predict("r2b_badcrc.png"), needles=("r2b_badcrc.png",)),
        read("r2b-zones-object-npz", lite_predict(zones="r2b_object.npz"),
             needles=("r2b_object.npz",)),
        read("r2b-zones-zip-not-npy", lite_predict(zones="r2b_not_npy.npz"),
             needles=("r2b_not_npy.npz",)),
        read("r2b-zones-json-list", lite_predict(zones="r2b_list.json"),
             needles=("r2b_list.json", "object")),
        read("r2b-zones-null-mean", lite_predict(zones="r2b_null_mean.json"),
             needles=("r2b_null_mean.json", "mean_m")),
        read("r2b-zones-ragged-hist", lite_predict(zones="r2b_ragged_hist.json"),
             needles=("r2b_ragged_hist.json",)),
        read("r2b-calib-fx-inf", [*lite_predict(), "--calib", "{in}/r2b_calib_inf_fx.json"],
             needles=("r2b_calib_inf_fx.json", "fx")),
        read("r2b-calib-distortion-text", [*lite_predict(), "--calib",
                                           "{in}/r2b_calib_distortion_text.json"],
             needles=("r2b_calib_distortion_text.json", "distortion")),
        read("r2b-calib-residual-null", [*lite_predict(), "--calib",
                                         "{in}/r2b_calib_residual_null.json"],
             needles=("r2b_calib_residual_null.json", "residuals.a")),
        read("r2b-replay-grid-fraction", ["replay", "{in}/r2b_rec_grid_frac", "--out", "{out}",
                                          *LITE], needles=("meta.json", "grid")),
        read("r2b-replay-number-line", ["replay", "{in}/r2b_rec_number_line", "--out",
                                        "{out}", *LITE], needles=("zones.jsonl:2",)),
        read("r2b-map-trajectory-utf16", ["map", rec, "--out", "{out}/m", "--trajectory",
                                          "{in}/r2b_traj_utf16.txt", *LITE],
             needles=("r2b_traj_utf16.txt",)),
        read("r2b-calibrate-garbage-ply", ["calibrate", cal, "--out", "{out}/c.json",
                                           "--slam-cloud", "{in}/r2b_garbage.ply",
                                           "--slam-trajectory", "{in}/r2b_traj_utf16.txt"],
             needles=("r2b_",)),
        path("r2b-checkpoint-dev-null", [*lite_predict()[:-4], "--checkpoint", "/dev/null"],
             needles=("/dev/null", "regular file")),
        path("r2b-check-official-folder", ["check-official", "{in}/empty"],
             needles=("empty", "folder")),
        path("r2b-layout-from-dev-null", ["export", "--preset", "deltar-lite", "--out",
                                          "{out}/m.onnx", "--layout-from", "/dev/null"],
             needles=("/dev/null", "regular file")),
        Case("r2c-calib-grid-4-for-8x8-zones", [*lite_predict(), "--calib",
                                                "{in}/r2c_calib_grid4.json"],
             needles=("--calib", "grid"), group="physical"),
        Case("r2c-replay-calib-640", ["replay", rec, "--out", "{out}", "--calib",
                                      "{in}/calib_640.json", *LITE],
             needles=("--calib", "480x640"), group="physical"),
        read("r2c-zone-count-text", lite_predict(zones="r2c_zone_count_text.json"),
             needles=("r2c_zone_count_text.json", "zone_count must be an integer")),
        physical("r2c-driver-mixed-lengths", lite_predict(zones="r2c_driver_mixed.json"),
                 needles=("r2c_driver_mixed.json", "same length")),
        Case("r2c-replay-offset-nan", ["replay", rec, "--out", "{out}", "--time-offset", "nan",
                                       *LITE], needles=("--time-offset",), group="options"),
        Case("r2c-replay-bag-overwrite", ["replay", "--bag", "{in}/empty", "--out-bag",
                                          "{out}/b", "--overwrite", *LITE],
             needles=("--overwrite", "--out folder"), group="options"),
        Case("r2c-replay-bag-offset-nan", ["replay", "--bag", "{in}/empty", "--out-bag",
                                           "{out}/b", "--time-offset", "nan", *LITE],
             needles=("--time-offset",), group="options"),
        Case("r2c-evaluate-depth-range-inverted", ["evaluate", "--data", zju, "--method",
                                                   "nearest", "--min-depth", "5",
                                                   "--max-depth", "1"],
             needles=("--min-depth",), group="options"),
        Case("r2c-evaluate-min-depth-nan", ["evaluate", "--data", zju, "--method", "nearest",
                                            "--min-depth", "nan"], needles=("--min-depth",),
             group="options"),
        Case("r2c-simulate-bias-nan", ["simulate", "procedural:2:0:48x64", "{out}/s",
                                       "--bias-mean", "nan", "--bias-prob", "0.5"],
             needles=("--bias-mean",), group="options"),
        Case("r2c-simulate-cnh-range-inverted", ["simulate", "procedural:2:0:48x64", "{out}/s",
                                                 "--cnh-range", "4:0.2"],
             needles=("--cnh-range",), group="options"),
        Case("r2c-record-wall-negative", ["record", "{out}/r", "--simulate", "wall:-1"],
             needles=("--simulate", "wall:-1"), group="options"),
        Case("r2c-record-wall-1e9", ["record", "{out}/r", "--simulate", "wall:1e9:2:48x64"],
             needles=("--simulate", "65.535"), group="physical", no_output=("r",)),
        Case("r2c-demo-frames-0", ["demo", "{out}/d", "--frames", "0"],
             needles=("--frames",), group="options"),
        Case("r2c-export-size-1x1", ["export", "--preset", "deltar-lite", "--out",
                                     "{out}/m.onnx", "--size", "1x1"],
             needles=("--size",), group="options", no_output=("m.onnx",)),
        Case("r2c-map-voxel-0", ["map", rec, "--out", "{out}/m", "--voxel", "0", *LITE],
             needles=("--voxel",), group="options"),
        Case("r2c-train-lr-negative", ["train", "--config", config, "--override",
                                       "optim.lr=-1", "--run-dir", "{out}/run"],
             needles=("optim.lr",), group="options"),
        Case("r2c-train-batch-0", ["train", "--config", config, "--override",
                                   "data.batch_size=0", "--run-dir", "{out}/run"],
             needles=("data.batch_size",), group="options"),
        Case("r2c-calibrate-tolerance-inf", ["calibrate", cal, "--out", "{out}/c.json",
                                             "--tolerance-s", "inf"],
             needles=("--tolerance-s",), group="options"),
        Case("r2c-bench-repeats-0", ["bench", "--repeats", "0"], needles=("--repeats",),
             group="options"),
        Case("r2c-fit-uncertainty-pixels-10", ["fit-uncertainty", "default", "--data", zju,
                                               "--out", "{out}/u.pt", "--pixels-per-frame",
                                               "10"], needles=("--pixels-per-frame",),
             group="options"),
        path("r2d-bag-dev-null", ["replay", "--bag", "/dev/null", "--out-bag", "{out}/b",
                                  *LITE], needles=("/dev/null", "bag")),
        path("r2d-bag-empty-folder", ["replay", "--bag", "{in}/empty", "--out-bag", "{out}/b",
                                      *LITE], needles=("empty", "bag")),
        path("r2d-bag-text-file", ["replay", "--bag", "{in}/outfile", "--out-bag", "{out}/b",
                                   *LITE], needles=("outfile", "bag")),
        path("r2d-map-trajectory-dev-null", ["map", rec, "--out", "{out}/m", "--trajectory",
                                             "/dev/null", *LITE],
             needles=("/dev/null", "regular file")),
        path("r2d-map-recording-a-file", ["map", "{in}/outfile", "--out", "{out}/m", *LITE],
             needles=("outfile", "not a folder")),
        read("r2d-fit-uncertainty-text-checkpoint", ["fit-uncertainty", "{in}/outfile",
                                                     "--data", zju, "--out", "{out}/u.pt"],
             needles=("outfile", "not a PyTorch file")),
        path("r2d-fit-uncertainty-data-dev-null", ["fit-uncertainty", "default", "--data",
                                                   "/dev/null", "--out", "{out}/u.pt"],
             needles=("/dev/null", "regular file")),
        path("r2d-demo-into-dev-null", ["demo", "/dev/null", "--frames", "1", "--size",
                                        "48x64"], needles=("/dev/null", "not a folder")),
        path("r2d-evaluate-checkpoint-dev-null", ["evaluate", "--data", zju, "--checkpoint",
                                                  "/dev/null"],
             needles=("/dev/null", "regular file")),
        path("r2d-evaluate-official-folder", ["evaluate", "--data", zju, "--official",
                                              "{in}/empty"], needles=("empty", "folder")),
        read("r2d-export-json-as-checkpoint", ["export", "--checkpoint", zju, "--out",
                                               "{out}/m.onnx"],
             needles=("data.json", "not a PyTorch file"), forbid=("Python objects",)),
        read("r2d-zones-hist-shape", lite_predict(zones="r2d_hist_shape.json"),
             needles=("r2d_hist_shape.json", "hist_counts")),
        Case("r2d-record-procedural-0", ["record", "{out}/r", "--simulate", "procedural:0"],
             needles=("--simulate", "frames"), group="options"),
        Case("r2d-simulate-procedural-0", ["simulate", "procedural:0", "{out}/s"],
             needles=("SRC", "frames"), group="options"),
        read("r2d-simulate-fake-mat", ["simulate", "{in}/r2d_fake.mat", "{out}/s"],
             needles=("r2d_fake.mat",)),
        path("r2d-train-resume-empty-folder", ["train", "--resume", "{in}/empty"],
             needles=("config.yaml", "not found")),
        physical("r2d-zones-valid-2", lite_predict(zones="r2d_valid_2.json"),
                 needles=("r2d_valid_2.json", "valid", "booleans")),
        physical("r2d-zones-valid-half-npz", lite_predict(zones="r2d_valid_half.npz"),
                 needles=("r2d_valid_half.npz", "valid", "booleans")),
        Case("r2d-replay-outputs-empty", ["replay", rec, "--out", "{out}", "--outputs", "",
                                          *LITE], needles=("--outputs",), group="options"),
        other("r2d-wall-test-recording-twice", ["wall-test", rec, rec, "--out", "{out}", *LITE],
              needles=("more than once",)),
        Case("r2d-evaluate-method-twice", ["evaluate", "--data", zju, "--method",
                                           "nearest,nearest"], expect="ok", group="options"),
        other("r2-folder-same-image-stem", ["predict", "--images", "{in}/r2_same_stem",
                                            "--zones-dir", "{in}/r2_same_stem", "--out",
                                            "{out}", *LITE], needles=("a.jpg", "a.png")),
        other("r2-folder-same-zone-stem", ["predict", "--images", "{in}/r2_same_zone_stem",
                                           "--zones-dir", "{in}/r2_same_zone_stem", "--out",
                                           "{out}", *LITE], needles=("a.json", "a.npz")),
        other("r2-replay-blank-zones", ["replay", "{in}/r2_rec_blank", "--out", "{out}",
                                        *LITE], needles=("nothing to replay",)),
        other("r2-replay-offset-beyond", ["replay", rec, "--out", "{out}", "--time-offset",
                                          "1000", *LITE], needles=("nothing to replay",
                                                                    "--tolerance")),
        other("r2-train-max-steps-negative", ["train", "--config", config, "--override",
                                              "trainer.max_steps=-5", "--run-dir",
                                              "{out}/run"], needles=("max_steps",)),
        other("r2-train-max-steps-0", ["train", "--config", config, "--override",
                                       "trainer.max_steps=0", "--run-dir", "{out}/run"],
              needles=("max_steps", "untrained")),
        # ---- the train / fit-uncertainty / simulate / calibrate / wall-test audit
        Case("r2e-check-calibration-tolerance-inf", ["check-calibration", cal, "--calib",
                                                     "{in}/calib.json", "--tolerance-s", "inf"],
             needles=("--tolerance-s", "finite"), group="options"),
        apart("r2e-calibrate-plot-is-out", ["calibrate", cal, "--out", "{out}/c", "--plot",
                                            "{out}/c"], needles=("--plot", "also --out"),
              no_output=("c",)),
        Case("r2e-train-design-size-0", ["train", "--config", config, "--override",
                                         "model.overrides.design_size=[0,0]", "--run-dir",
                                         "{out}/run"], needles=("design_size", "positive"),
             no_output=("run",), group="options"),
        Case("r2e-train-source-seed-negative", ["train", "--config", config, "--override",
                                                "data.sources.0.seed=-1", "--run-dir",
                                                "{out}/run"],
             needles=("data.sources.0.seed", ">= 0"), no_output=("run",), group="options"),
        # Found when the data is opened, after the network is built: not "early".
        other("r2e-train-one-frame-to-hold-out", ["train", "--config", config, "--override",
                                                  "data.sources.0.frames=1", "--run-dir",
                                                  "{out}/run"],
              needles=("data.sources.0", "at least 2 frames"), early=False,
              no_output=("run/config.yaml",)),
        Case("r2e-train-val-check-interval-100", ["train", "--config", config, "--override",
                                                  "trainer.val_check_interval=100",
                                                  "--run-dir", "{out}/run"],
             needles=("trainer.val_check_interval", "4 batches"), early=False,
             no_output=("run/config.yaml",), group="options"),
        Case("r2e-train-limit-val-fraction", ["train", "--config", config, "--override",
                                              "trainer.limit_val_batches=0.5", "--run-dir",
                                              "{out}/run"],
             needles=("trainer.limit_val_batches", "less than one batch"), early=False,
             no_output=("run/config.yaml",), group="options"),
        path("r2e-train-output-dir-file", ["train", "--config", config, "--override",
                                           "output_dir={in}/outfile"],
             needles=("output_dir", "is a file")),
        Case("r2e-wall-test-calib-640", ["wall-test", rec, "--out", "{out}", "--calib",
                                         "{in}/calib_640.json", *LITE],
             needles=("--calib", "480x640"), group="options"),
        Case("r2e-fit-uncertainty-too-few-pixels", ["fit-uncertainty", "default", "--data", zju,
                                                    "--out", "{out}/u.pt", "--frames-per-set",
                                                    "1", "--pixels-per-frame", "100"],
             needles=("--pixels-per-frame", "at most 100"), no_output=("u.pt",),
             group="options"),
        Case("r2e-simulate-split-empty", ["simulate", "procedural:1:0:48x64", "{out}/s",
                                          "--split", ""], needles=("--split", "non-empty"),
             no_output=("s",), group="options"),
    ]


# ---------------------------------------------------------------------------- running
def _digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha1(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


def _normalise(text: str) -> str:
    return " ".join(_BOX.sub(" ", text).split()).lower()


def _count_models() -> Callable[[], int]:
    """Count network constructions (``DepthEstimator.__init__`` calls)."""
    from deltar.inference.estimator import DepthEstimator

    calls = [0]
    original = DepthEstimator.__init__

    def counting(self, *args, **kwargs):
        calls[0] += 1
        original(self, *args, **kwargs)

    DepthEstimator.__init__ = counting
    return lambda: calls[0]


def run_case(case: Case, inp: Path, out: Path, cli, models: Callable[[], int]) -> Outcome:
    """Run one case and classify it."""
    out.mkdir(parents=True, exist_ok=True)
    if case.setup is not None:
        case.setup(inp, out)
    before = models()
    start = time.perf_counter()
    flags: list[str] = []
    if callable(case.run):
        stderr = io.StringIO()
        try:
            with contextlib.redirect_stderr(stderr), warnings.catch_warnings():
                warnings.simplefilter("ignore")
                value = case.run(inp, out)
            failed, text, escaped = False, f"{value!r}"[:300], False
        except _Silent as err:
            return Outcome("silent", str(err), time.perf_counter() - start)
        except (ValueError, TypeError, FileNotFoundError, FileExistsError) as err:
            failed, text, escaped = True, f"{type(err).__name__}: {err}", False
        except Exception as err:  # anything else reaches the user as a traceback
            failed, text, escaped = True, f"{type(err).__name__}: {err}", True
    else:
        args = [a.replace("{in}", str(inp)).replace("{out}", str(out)) for a in case.run]
        result = cli(args)
        text = result.output
        escaped = result.exception is not None and not isinstance(result.exception,
                                                                  SystemExit)
        if escaped:
            text += f"\n{type(result.exception).__name__}: {result.exception}"
        failed = result.exit_code != 0
    seconds = time.perf_counter() - start
    norm = _normalise(text)
    found = all(n.lower() in norm for n in case.needles)
    forbidden = any(f.lower() in norm for f in case.forbid)
    if escaped:
        verdict = "traceback"
    elif case.expect == "ok":
        verdict = "correct" if not failed and found else ("misleading" if failed else "silent")
    elif not failed:
        verdict = "silent"
    else:
        verdict = "clear" if found and not forbidden else "misleading"
    if failed and case.early and not callable(case.run) and models() > before:
        flags.append("late")
    if failed and any((out / p).exists() for p in case.no_output):
        flags.append("partial")
    if failed and any(p.name.endswith(".tmp") or ".tmp." in p.name for p in out.rglob(".*")):
        flags.append("partial")
    return Outcome(verdict, text, seconds, flags)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--verbose", action="store_true", help="print every case's output")
    parser.add_argument("--only", default=None, help="run only cases whose name contains this")
    parser.add_argument("--skip", action="append", default=[],
                        help="leave out cases whose name contains this (repeatable; e.g. "
                        "cases that crash the whole process on an older version)")
    parser.add_argument("--json", type=Path, default=None, help="write the verdicts here")
    args = parser.parse_args(argv)

    os.environ.pop("DISPLAY", None)
    os.environ.pop("WAYLAND_DISPLAY", None)
    os.environ.setdefault("COLUMNS", "200")
    from typer.testing import CliRunner

    import deltar
    from deltar.cli.main import app

    runner = CliRunner()

    def cli(cli_args):
        return runner.invoke(app, cli_args)

    models = _count_models()
    with tempfile.TemporaryDirectory(prefix="deltar-sweep-") as tmp:
        root = Path(tmp)
        inp = build_inputs(root)
        build_recordings(inp, cli)
        build_round2_inputs(inp)
        digest = _digest(inp)
        selected = [c for c in (*cases(), *round2_cases())
                    if (args.only is None or args.only in c.name)
                    and not any(skip in c.name for skip in args.skip)]
        outcomes: dict[str, Outcome] = {}
        for index, case in enumerate(selected):
            outcome = run_case(case, inp, root / "out" / f"{index:03d}", cli, models)
            now = _digest(inp)
            if now != digest:
                outcome.flags.append("modified")
                changed = sorted(k for k in set(now) | set(digest) if now.get(k) != digest.get(k))
                outcome.text += f"\n(inputs changed: {changed})"
                digest = now
            outcomes[case.name] = outcome
            marks = f" [{', '.join(outcome.flags)}]" if outcome.flags else ""
            print(f"{outcome.verdict:10s} {outcome.seconds:6.2f} s  {case.name}{marks}")
            if args.verbose or outcome.verdict in ("traceback", "silent", "misleading"):
                lines = outcome.text.strip().splitlines()
                shown = lines[:3] + (["..."] if len(lines) > 6 else []) + lines[3:][-3:]
                for line in shown:
                    print(f"{'':20s}| {line[:160]}")
    verdicts = Counter(o.verdict for o in outcomes.values())
    flags = Counter(f for o in outcomes.values() for f in set(o.flags))
    print(f"\ndeltar from {Path(deltar.__file__).parent}")
    print(f"{len(outcomes)} cases: " + ", ".join(f"{verdicts.get(k, 0)} {k}" for k in (
        "clear", "correct", "traceback", "silent", "misleading")))
    print("flags: " + ", ".join(f"{flags.get(k, 0)} {k}" for k in ("late", "partial",
                                                                  "modified")))
    groups = sorted({c.group for c in selected if c.group})
    for group in groups:
        names = [c.name for c in selected if c.group == group]
        good = sum(outcomes[n].verdict in ("clear", "correct") and not outcomes[n].flags
                   for n in names)
        print(f"  {group}: {len(names)} cases, {good} handled, {len(names) - good} not")
    if args.json is not None:
        args.json.write_text(json.dumps({name: {"verdict": o.verdict, "flags": o.flags,
                                                "seconds": round(o.seconds, 3)}
                                         for name, o in outcomes.items()}, indent=1) + "\n")
    bad = sum(verdicts.get(k, 0) for k in ("traceback", "silent", "misleading"))
    return 1 if bad or flags else 0


if __name__ == "__main__":
    sys.exit(main())
