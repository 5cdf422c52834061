"""Measure an install of this package in a new virtualenv: its size, and that it runs.

Creates a virtualenv, installs the project (``pip install PROJECT[EXTRAS]``), reports
the size of the virtualenv's site-packages (``du -sk``, as ``du -sh`` counts), the
largest distributions in it and whether PyTorch is importable there; then, with
``--run``, runs ``deltar demo`` and ``deltar predict`` on the demo's sample inside the
virtualenv (the README's main job), timing each. Prints one summary and optionally
writes it as JSON.

    python benchmarks/install_size.py --venv /tmp/venv-base                  # base install
    python benchmarks/install_size.py --venv /tmp/venv-train --extras train --no-run
    python benchmarks/install_size.py --venv /tmp/venv-base --reuse --run   # runs only

Needs network access to the package index (pip downloads the wheels).
"""

from __future__ import annotations

import argparse
import json
import platform
import shutil
import subprocess
import sys
import time
from pathlib import Path

PROJECT = Path(__file__).resolve().parents[1]


def run(command: list[str], **kwargs) -> subprocess.CompletedProcess:
    """Run a command, raising with its output when it fails."""
    result = subprocess.run(command, capture_output=True, text=True, **kwargs)
    if result.returncode != 0:
        raise SystemExit(f"failed ({result.returncode}): {' '.join(command)}\n"
                         f"{result.stdout[-3000:]}\n{result.stderr[-3000:]}")
    return result


def site_packages(venv: Path) -> Path:
    """The virtualenv's site-packages folder."""
    found = sorted(venv.glob("lib/python*/site-packages"))
    if not found:
        raise SystemExit(f"{venv}: no lib/python*/site-packages")
    return found[0]


def disk_usage_mb(path: Path) -> float:
    """Disk usage of ``path`` in MiB, as ``du -sk`` counts it."""
    return int(run(["du", "-sk", str(path)]).stdout.split()[0]) / 1024


def largest_entries(folder: Path, count: int = 8) -> list[tuple[str, float]]:
    """The ``count`` largest top-level entries of ``folder``: (name, MiB)."""
    sizes = [(entry.name, disk_usage_mb(entry)) for entry in folder.iterdir()
             if not entry.name.endswith((".dist-info", ".pth")) and entry.name != "__pycache__"]
    return sorted(sizes, key=lambda item: -item[1])[:count]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--venv", type=Path, required=True, help="virtualenv folder (created)")
    parser.add_argument("--extras", default="", help="extras to install, e.g. train or dev")
    parser.add_argument("--project", type=Path, default=PROJECT, help="project to install")
    parser.add_argument("--reuse", action="store_true", help="use an existing virtualenv "
                        "as it is (no new install)")
    parser.add_argument("--run", dest="run", action="store_true", default=True,
                        help="run deltar demo and deltar predict in it (default)")
    parser.add_argument("--no-run", dest="run", action="store_false")
    parser.add_argument("--work", type=Path, default=None, help="folder for the demo's "
                        "outputs (default: <venv>-work)")
    parser.add_argument("--json", type=Path, default=None, help="write the summary here")
    args = parser.parse_args()

    venv = args.venv.resolve()
    python = venv / "bin" / "python"
    summary: dict = {"date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
                     "machine": f"{platform.machine()} {platform.system()}, "
                                f"Python {platform.python_version()}",
                     "extras": args.extras or "(base)"}
    if not args.reuse:
        if venv.exists():
            raise SystemExit(f"{venv} exists; remove it or pass --reuse")
        run([sys.executable, "-m", "venv", str(venv)])
        target = str(args.project.resolve()) + (f"[{args.extras}]" if args.extras else "")
        start = time.perf_counter()
        run([str(python), "-m", "pip", "install", "--quiet", target])
        summary["install_s"] = round(time.perf_counter() - start, 1)
        summary["command"] = f"python -m venv {venv} && {venv}/bin/pip install {target}"
    packages = site_packages(venv)
    summary["site_packages_mb"] = round(disk_usage_mb(packages), 1)
    summary["venv_mb"] = round(disk_usage_mb(venv), 1)
    summary["largest"] = [[name, round(mb, 1)] for name, mb in largest_entries(packages)]
    probe = ("import importlib.util as u; "
             "print(*[n for n in ('torch', 'timm', 'lightning', 'einops', 'onnxruntime', "
             "'cv2') if u.find_spec(n)])")
    summary["importable"] = run([str(python), "-c", probe]).stdout.split()
    if args.run:
        work = (args.work or Path(f"{venv}-work")).resolve()
        if work.exists():
            shutil.rmtree(work)
        work.mkdir(parents=True)
        deltar = str(venv / "bin" / "deltar")
        start = time.perf_counter()
        run([deltar, "demo", str(work / "deltar-demo")], cwd=work)
        summary["demo_s"] = round(time.perf_counter() - start, 1)
        sample = work / "deltar-demo" / "sample"
        start = time.perf_counter()
        out = run([deltar, "predict", "--image", str(sample / "image.png"), "--zones",
                   str(sample / "zones.json"), "--calib", str(sample / "calib.json"),
                   "--out", str(work / "pred")], cwd=work)
        summary["predict_s"] = round(time.perf_counter() - start, 1)
        summary["predict_output"] = out.stdout.strip().splitlines()[-1]
        metrics = json.loads((work / "deltar-demo" / "metrics.json").read_text())
        model = metrics.get("model:default", {})
        summary["demo_model_rel_rmse"] = [round(model.get("rel", float("nan")), 4),
                                          round(model.get("rmse", float("nan")), 4)]
    print(json.dumps(summary, indent=2))
    if args.json is not None:
        args.json.write_text(json.dumps(summary, indent=2) + "\n")


if __name__ == "__main__":
    main()
