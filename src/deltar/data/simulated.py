"""Simulated ZJU-L5-layout sets on disk (``deltar simulate``, the demo): RGB-D frames with
zone readings simulated from their depth (:func:`simulate_set`).

The torch Dataset that simulates the zones of every training item on the fly is
:class:`deltar.training.datasets.SimulatedL5Dataset`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from deltar.data.rgbd import RGBDFrame
from deltar.sensor.augment import SignalAugmentation, training_zone_rects
from deltar.sensor.geometry import zone_rects
from deltar.sensor.simulator_config import SimulatorConfig
from deltar.sensor.targets import readings_changed

#: Zone layouts of :func:`simulate_set` (``deltar simulate --layout``).
SET_LAYOUTS: tuple[str, ...] = ("calibrated", "aligned")


def simulate_set(source: Sequence[RGBDFrame], out, indices: Sequence[int] | None = None, *,
                 grid: int = 8, layout: str = "calibrated",
                 degrade: SignalAugmentation | None = None, seed: int = 0,
                 cnh_config=None, scene: str = "scene", split: str = "test",
                 no_target_flags: bool = True, max_targets: int = 1, on_frame=None):
    """Simulate L5 readings for RGB-D frames and write them as a ZJU-L5-layout set.

    Args:
        source: RGB-D frames (any reader of :mod:`deltar.data.sources`).
        out: output folder (written by :func:`deltar.data.zju_l5.write_zju_l5`).
        indices: frame numbers of ``source`` to use, each in ``0..len(source) - 1`` (all
            by default). Negative numbers are refused, not counted from the end: a frame's
            degradation and its place in the set follow its number.
        grid: zones per side (4 or 8).
        layout: ``calibrated`` (the 45 x 45 deg FoV projected with each frame's
            intrinsics) or ``aligned`` (the release's 56 px grid centred in the image,
            scaled with the width;
            112 px zones for a 4x4 grid, the same field of view).
        degrade: optional signal degradation (zones dropped, means biased); frame ``i``
            draws from ``(seed, i)``.
        seed: seed of the degradation.
        cnh_config: optional :class:`~deltar.sensor.cnh.CNHConfig`: also write ideal
            compact normalised histograms.
        scene: prefix of the sample names (``scene/frame``).
        split: split name written to ``data.json``.
        no_target_flags: write the zones that reported no target (``zone_no_target``);
            ``False`` writes none, as the released ZJU-L5 files store none (those zones
            are then just invalid).
        max_targets: targets per zone to report, 1..4 (1: the primary reading alone; more
            writes every zone's targets, :func:`~deltar.sensor.simulate_frame.simulate_zone_frame`).
            A degradation scales a zone's other targets as it scales its primary reading
            and drops them with it (and those it pushes past the range).
        on_frame: optional callable called after each frame (progress).

    Returns:
        ``(index_path, valid_counts)``: the written ``data.json`` and the number of valid
        zones of each frame.
    """
    from deltar.data.zju_l5 import ZJUL5Sample, write_zju_l5
    from deltar.sensor.zone_frame import ZoneFrame

    if grid not in (4, 8):
        raise ValueError(f"grid must be 4 or 8, got {grid}")
    if layout not in SET_LAYOUTS:
        raise ValueError(f"layout must be one of {SET_LAYOUTS}, got {layout!r}")
    indices = list(range(len(source))) if indices is None else list(indices)
    bad = [i for i in indices if isinstance(i, bool) or not isinstance(i, int | np.integer)
           or not 0 <= i < len(source)]
    if bad:  # before any frame is simulated or written
        more = f" (and {len(bad) - 1} more)" if len(bad) > 1 else ""
        raise ValueError(f"indices must be frame numbers in 0..{len(source) - 1} of the "
                         f"{len(source)} frames of source, got {bad[0]!r}{more}")
    valid_counts: list[int] = []

    def simulated(frame: RGBDFrame, index: int) -> ZJUL5Sample:
        from deltar.sensor.simulate_frame import simulate_zone_frame

        height, width = frame.depth_m.shape
        if layout == "calibrated":
            rects = zone_rects(frame.intrinsics, grid)
        else:
            zone_px = max(1, round(56 * 8 / grid * width / 640))  # the same FoV
            rects = training_zone_rects(height, width, grid=grid, zone_px=zone_px)
        zones = simulate_zone_frame(frame.depth_m, rects, max_targets=max_targets)
        targets = {}
        if max_targets > 1:
            # (Z, T) each, as the ZJU-L5 files store them.
            targets = {name: getattr(zones, name).reshape(grid * grid, -1)
                       for name in ("target_mean_m", "target_sigma_m", "target_valid",
                                    "target_signal")}
        if degrade is not None:
            import torch  # the augmentation is the training pipeline's (PyTorch)

            generator = torch.Generator().manual_seed(seed * 1_000_003 + index)
            # The augmentation works on a frame's flat (Z,) zones, not per grid row.
            mean, sigma, valid = degrade(torch.from_numpy(zones.mean_m.reshape(-1)),
                                         torch.from_numpy(zones.sigma_m.reshape(-1)),
                                         torch.from_numpy(zones.valid.reshape(-1)), generator)
            # A reading biased past the sensor's range is one it does not report.
            valid = valid & (mean > 0) & (mean <= SimulatorConfig().max_range_m)
            mean, sigma = mean * valid, sigma * valid
            if targets:
                targets = readings_changed(targets, zones.mean_m.reshape(-1), mean.numpy(),
                                           sigma.numpy(), valid.numpy(),
                                           SimulatorConfig().max_range_m)
            zones = ZoneFrame(*(a.numpy().reshape(grid, grid) for a in (mean, sigma, valid)),
                              no_target=zones.no_target)
        valid_counts.append(int(np.count_nonzero(zones.valid)))
        histogram = {}
        if cnh_config is not None:
            from deltar.sensor.cnh import simulate_cnh

            histogram = {"hist_edges_m": cnh_config.edges_m(),
                         "hist_counts": simulate_cnh(frame.depth_m, rects, cnh_config)}
        return ZJUL5Sample(rgb=frame.image, depth_m=frame.depth_m,
                           zone_mean_sigma=zones.mean_sigma(), zone_rects=rects,
                           zone_valid=zones.valid.reshape(-1),
                           zone_no_target=zones.flat_no_target() if no_target_flags else None,
                           name=f"{scene}/{frame.name}".replace("\\", "/"),
                           intrinsics=frame.intrinsics, **histogram, **targets)

    def samples():
        for i in indices:
            yield simulated(source[i], i)
            if on_frame is not None:
                on_frame()

    return write_zju_l5(out, samples(), split=split), valid_counts
