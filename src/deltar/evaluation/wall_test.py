"""Flat-wall test: bias and jitter of predicted depth on recordings of a flat wall.

For each recording (the rig facing a flat wall at one distance), every replayed frame
is compared with a plane: the plane fitted robustly to the recording's reference
depth when it has one (simulated rigs, or a depth camera), else to the evaluated
depth map itself (then bias measures how far from flat the map is). Both the
network's depth and the raw sensor (each valid zone's mean painted over its pixels)
are evaluated on the same pixels, those covered by valid zones, with
:func:`deltar.evaluation.plane.plane_metrics` (bias = mean absolute error to the plane,
jitter = standard deviation of the signed error, inliers only). Per recording the
frame values are averaged; the distance is the median of the valid zone means. A
recording whose plane fit keeps under :data:`MIN_WALL_INLIER_FRACTION` of the pixels as
inliers (averaged over its frames) is warned about: it does not look like one flat wall.

Flat-wall scenes to record (simulated rigs) are :mod:`deltar.data.flat_wall`.
"""

from __future__ import annotations

import csv
import io
import json
import os
import warnings
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from deltar.camera import backproject
from deltar.capture.replay import replay
from deltar.evaluation.plane import fit_plane, plane_metrics
from deltar.io.atomic import atomic_path, write_text_atomic
from deltar.sensor.geometry import zone_rects_to_pixel_bounds
from deltar.sensor.placement import zone_mean_depth

if TYPE_CHECKING:
    from deltar.calibration.rig import RigCalibration
    from deltar.inference.estimator import DepthEstimator

METHODS = ("network", "zones")
#: Below this mean fraction of the fitted plane's inliers a recording is warned about.
#: A flat wall keeps nearly all (simulated walls 1.00; depth noise of 3 cm at 3 m 1.00,
#: with 20 % of the pixels gross outliers 0.83); rooms (``--simulate procedural:8``)
#: keep 0.53 to 0.88 per frame, 0.64 averaged.
MIN_WALL_INLIER_FRACTION = 0.8


@dataclass
class WallResult:
    """Flat-wall numbers of one recording (metres).

    Attributes:
        recording: the recording folder.
        distance_m: median valid zone mean over the recording.
        frames: frames evaluated.
        reference: ``"depth"`` (plane from the recorded depth) or ``"self"``.
        network_bias_m, network_jitter_m: the estimator's depth.
        zones_bias_m, zones_jitter_m: the raw zone means.
    """

    recording: str
    distance_m: float
    frames: int
    reference: str
    network_bias_m: float
    network_jitter_m: float
    zones_bias_m: float
    zones_jitter_m: float


def evaluate_recording(recording: str | os.PathLike, estimator: DepthEstimator, *,
                       calibration: RigCalibration | None = None, tolerance_s: float = 0.02,
                       every: int = 1, limit: int | None = None) -> WallResult:
    """Flat-wall bias and jitter of one recording (see the module docstring).

    Warns (once, naming the recording) when its plane fits keep under
    :data:`MIN_WALL_INLIER_FRACTION` of the pixels on average: the fit to the reference
    depth, or without one the network depth's fit to itself.

    Raises:
        ValueError: no frame could be evaluated (no valid zones, no pairs).
    """

    values: dict[str, list[tuple[float, float]]] = {m: [] for m in METHODS}
    distances: list[float] = []
    on_plane: list[float] = []  # each frame's fraction of plane-fit inliers
    reference_kind = "self"
    for item in replay(recording, estimator, calibration=calibration,
                       tolerance_s=tolerance_s, every=every, limit=limit):
        pred = item.prediction
        size = pred.depth_m.shape
        mean, _, valid = pred.zone_frame.flat()
        if not valid.any():
            continue
        mask = np.zeros(size, dtype=bool)
        for y0, x0, y1, x1 in zone_rects_to_pixel_bounds(pred.zone_rects[valid], *size):
            mask[y0:y1, x0:x1] = True
        plane = None
        if item.reference_depth_m is not None and (item.reference_depth_m[mask] > 0).sum() >= 3:
            plane, inliers = fit_plane(backproject(item.reference_depth_m, pred.intrinsics,
                                                   mask))
            reference_kind = "depth"
            on_plane.append(float(np.mean(inliers)))
        zones_map = zone_mean_depth(pred.zone_frame, pred.zone_rects, size)
        for method, depth in (("network", pred.depth_m), ("zones", zones_map)):
            metrics = plane_metrics(depth, pred.intrinsics, plane=plane, mask=mask)
            values[method].append((metrics.bias_m, metrics.jitter_m))
            if plane is None and method == "network":  # the map fitted to itself
                on_plane.append(metrics.inlier_fraction)
        distances.append(float(np.median(mean[valid])))
    if not distances:
        raise ValueError(f"{recording}: no frame with valid zones and a colour image to "
                         "evaluate")
    if np.mean(on_plane) < MIN_WALL_INLIER_FRACTION:
        what = "reference depth" if reference_kind == "depth" else "network depth"
        warnings.warn(f"{recording}: the plane fitted to its {what} keeps only "
                      f"{np.mean(on_plane):.0%} of the pixels as inliers (mean over "
                      f"{len(on_plane)} frames; a flat wall keeps over "
                      f"{MIN_WALL_INLIER_FRACTION:.0%}): it does not look like one flat wall, "
                      "so its bias and jitter are not a wall's", stacklevel=2)
    net = np.mean(values["network"], axis=0)
    zones = np.mean(values["zones"], axis=0)
    return WallResult(recording=str(recording), distance_m=float(np.median(distances)),
                      frames=len(distances), reference=reference_kind,
                      network_bias_m=float(net[0]), network_jitter_m=float(net[1]),
                      zones_bias_m=float(zones[0]), zones_jitter_m=float(zones[1]))


def wall_test(recordings: Sequence[str | os.PathLike], estimator: DepthEstimator,
              **kwargs) -> list[WallResult]:
    """:func:`evaluate_recording` for each recording, sorted by distance."""
    if not recordings:
        raise ValueError("give at least one recording")
    results = [evaluate_recording(r, estimator, **kwargs) for r in recordings]
    return sorted(results, key=lambda r: r.distance_m)


def result_paths(out_dir: str | os.PathLike) -> dict[str, Path]:
    """The files :func:`write_results` writes in ``out_dir``: kind ("json", "csv",
    "plot") -> path."""
    out = Path(out_dir)
    return {"json": out / "wall_test.json", "csv": out / "wall_test.csv",
            "plot": out / "wall_test.png"}


def write_results(out_dir: str | os.PathLike, results: Sequence[WallResult], *,
                  title: str = "", overwrite: bool = False) -> dict[str, Path]:
    """Write ``wall_test.json``, ``wall_test.csv`` and the plot ``wall_test.png``.

    The plot needs matplotlib (the ``plots`` extra); without it a ``UserWarning`` says
    so and the two tables are written alone.

    Returns:
        dict kind ("json", "csv", "plot") -> path; no "plot" without matplotlib.
    """
    from deltar.io.render import has_matplotlib

    rows = [asdict(r) for r in results]
    paths = result_paths(out_dir)
    if not has_matplotlib():
        del paths["plot"]
    existing = [str(p) for p in paths.values() if p.exists()]
    if existing and not overwrite:  # none written unless all can be: no mixed result set
        raise FileExistsError(f"refusing to overwrite {', '.join(existing)}; pass "
                              "--overwrite to replace them")
    write_text_atomic(paths["json"], json.dumps({"title": title, "results": rows}, indent=2)
                      + "\n", overwrite=overwrite)
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=list(rows[0]) if rows else ["recording"])
    writer.writeheader()
    writer.writerows(rows)
    write_text_atomic(paths["csv"], buffer.getvalue(), overwrite=overwrite)
    if "plot" not in paths:
        import warnings

        warnings.warn('wall_test.png needs matplotlib, which the \'plots\' extra installs: '
                      'pip install "deltar[plots]"', UserWarning, stacklevel=2)
        return paths
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    distance = [r.distance_m for r in results]
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    try:
        for ax, key, label in ((axes[0], "bias", "bias (mean |error|)"),
                               (axes[1], "jitter", "jitter (std of error)")):
            for method, marker in (("network", "o-"), ("zones", "s--")):
                ax.plot(distance, [1000 * getattr(r, f"{method}_{key}_m") for r in results],
                        marker, label=method)
            ax.set_xlabel("distance to wall (m)")
            ax.set_ylabel("mm")
            ax.set_title(label)
            ax.grid(alpha=0.3)
            ax.legend()
        if title:
            fig.suptitle(title)
        fig.tight_layout()
        with atomic_path(paths["plot"], overwrite=overwrite) as tmp:
            fig.savefig(tmp, format="png", dpi=100)
    finally:
        plt.close(fig)
    return paths
