"""The torch Datasets of training; every item a dict of tensors.

:class:`SimulatedL5Dataset` turns any RGB-D reader into items with a simulated L5
signal: read the frame, optionally augment the image (crop, rotation, flip, colour),
place the zones on the final image, simulate the zone readings from its depth
(:mod:`deltar.sensor.simulate`), optionally augment the signal (drop zones, noisy means)
and sample the depth hypotheses the network consumes. :class:`ZJUL5TrainingDataset` does
the same for samples with real zone readings, :class:`IndexedConcat` joins datasets and
numbers their items. All randomness of item ``i`` in epoch ``e`` comes from
``(seed, e, i)``, so a run is reproducible whatever the worker layout.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch.utils.data import ConcatDataset, Dataset

from deltar.camera import CameraIntrinsics
from deltar.contract import IMAGENET_MEAN, IMAGENET_STD, normalise_image
from deltar.data.rgbd import RGBDFrame
from deltar.data.transforms import ImageAugmentation, flip_intrinsics
from deltar.sensor.augment import SignalAugmentation, training_zone_rects
from deltar.sensor.geometry import DEFAULT_FOV_DEG, mirror_zone_rects, zone_rects
from deltar.sensor.sampling import sample_hypotheses, sample_hypotheses_from_histogram
from deltar.sensor.simulate import simulate_zones
from deltar.sensor.simulate_frame import check_target_options
from deltar.sensor.simulator_config import SimulatorConfig
from deltar.sensor.targets import (
    NETWORK_TARGET_SLOTS,
    fixed_target_slots,
    readings_changed,
    target_inputs,
)
from deltar.sensor.zone_frame import ZoneFrame
from deltar.training.config import ZONE_LAYOUTS


class SimulatedL5Dataset(Dataset):
    """A torch dataset of RGB-D frames with simulated multi-zone ToF readings.

    Args:
        reader: any sequence of :class:`~deltar.data.rgbd.RGBDFrame` (``open_rgbd``,
            ``NYUH5Reader``, ``ProceduralReader``, ...).
        zone_layout: where the zones fall in the (final) image:

            - ``"calibrated"``: the sensor's FoV (``fov_deg``) split into ``grid`` x ``grid``
              zones, projected with the frame's intrinsics (``deltar.sensor.zone_rects``,
              sensor at the camera centre).
            - ``"training"``: the release's training layout, ``training_grid`` x
              ``training_grid`` zones of ``training_zone_px`` pixels centred in the image,
              shifted by up to ``training_max_offset_px`` pixels.
            - a (Z, 4) array of rectangles (y0, x0, y1, x1) in pixels of the reader's images
              (e.g. from a real rig's calibration); crops shift them and flips mirror them
              (and their order, so zones stay row-major in the image).
        grid: zones per side for the calibrated layout (4 or 8).
        fov_deg: sensor (horizontal, vertical) field of view in degrees.
        training_grid, training_zone_px, training_max_offset_px: the training layout.
        simulator: zone simulator parameters (``SimulatorConfig()`` by default).
        signal_augmentation: optional zone dropping / mean noise (training).
        image_augmentation: optional crop / rotation / flip / colour jitter (training).
        num_hypotheses: K, depth hypotheses per zone.
        sampling: ``"icdf"`` or ``"uniform"`` (see ``deltar.sensor.sampling``).
        seed: base seed of all randomness.
        depth_scale_range: optional (low, high): scale the whole scene's depth by a
            factor drawn log-uniformly from it before the zones are simulated (a scaled
            scene images the same, so ground truth and zones scale together; the
            sensor's range limit still applies). None: no scaling.
        layout_jitter_px: calibration error: the rectangles handed to the network (not
            those the zones were simulated with) are shifted by one offset drawn
            uniformly within +- this many pixels in x and y.
        layout_rotation_deg: calibration error: the handed-out zone centres are also
            rotated about the image centre by up to +- this many degrees.
        image_mean, image_std: per-channel normalisation of ``image`` (the network's
            input contract, ``model.network_config.inputs.image_mean`` / ``image_std``).
        max_targets: targets per zone the simulated sensor reports (1..4, ST's
            targets-per-zone setting); above 1 items also carry ``zone_targets``.

    Items are dicts of tensors: ``image`` (3, H, W) float32 ImageNet-normalised,
    ``image_rgb`` (H, W, 3) uint8, ``depth`` (1, H, W) float32 metres (0 invalid),
    ``zone_mean_sigma`` (Z, 2) float32 metres, ``zone_valid`` (Z,) bool,
    ``zone_no_target`` (Z,) bool (invalid zones with no target in range), ``zone_rects``
    (Z, 4) float32 pixels, ``hypotheses`` (Z, K) float32 metres, ``intrinsics`` (4,) float32
    fx, fy, cx, cy in pixels of the returned image; with ``max_targets`` > 1 also
    ``zone_targets`` (Z, NETWORK_TARGET_SLOTS, 2) float32 ``[metres, share]``
    (:func:`deltar.sensor.targets.target_inputs` of the reading as augmented).
    """

    def __init__(
        self,
        reader: Sequence[RGBDFrame],
        *,
        zone_layout: str | np.ndarray = "calibrated",
        grid: int = 8,
        fov_deg: tuple[float, float] = DEFAULT_FOV_DEG,
        training_grid: int = 6,
        training_zone_px: int = 64,
        training_max_offset_px: int = 0,
        simulator: SimulatorConfig | None = None,
        signal_augmentation: SignalAugmentation | None = None,
        image_augmentation: ImageAugmentation | None = None,
        num_hypotheses: int = 16,
        sampling: str = "icdf",
        seed: int = 0,
        depth_scale_range: tuple[float, float] | None = None,
        layout_jitter_px: float = 0.0,
        layout_rotation_deg: float = 0.0,
        image_mean: Sequence[float] = IMAGENET_MEAN,
        image_std: Sequence[float] = IMAGENET_STD,
        max_targets: int = 1,
    ) -> None:
        check_target_options(max_targets, "strongest")
        self.max_targets = int(max_targets)
        if isinstance(zone_layout, str):
            if zone_layout not in ZONE_LAYOUTS:
                raise ValueError(f"zone_layout must be one of {ZONE_LAYOUTS} or a (Z, 4) "
                                 f"array, got {zone_layout!r}")
            self._fixed_rects = None
        else:
            rects = np.asarray(zone_layout, dtype=np.float32)
            zones = rects.shape[0] if rects.ndim == 2 else 0
            side = math.isqrt(zones)
            if rects.ndim != 2 or rects.shape[1] != 4 or side * side != zones or zones == 0:
                raise ValueError(f"zone_layout array must be (n * n, 4), got {rects.shape}")
            if not np.all(np.isfinite(rects)):
                raise ValueError("zone_layout array has NaN or infinite values")
            self._fixed_rects = rects
            zone_layout = "fixed"
        if grid not in (4, 8):
            raise ValueError(f"grid must be 4 or 8, got {grid}")
        if len(reader) == 0:
            raise ValueError("reader has no frames")
        if depth_scale_range is not None and not 0 < depth_scale_range[0] <= depth_scale_range[1]:
            raise ValueError(f"depth_scale_range must be (low, high) with 0 < low <= high, got "
                             f"{depth_scale_range}")
        if layout_jitter_px < 0 or layout_rotation_deg < 0:
            raise ValueError("layout_jitter_px and layout_rotation_deg must be >= 0")
        self.depth_scale_range = depth_scale_range
        self.layout_jitter_px = float(layout_jitter_px)
        self.layout_rotation_deg = float(layout_rotation_deg)
        self.image_mean = tuple(float(v) for v in image_mean)
        self.image_std = tuple(float(v) for v in image_std)
        self.reader = reader
        self.zone_layout = zone_layout
        self.grid = grid
        self.fov_deg = fov_deg
        self.training_grid = training_grid
        self.training_zone_px = training_zone_px
        self.training_max_offset_px = training_max_offset_px
        self.simulator = simulator or SimulatorConfig()
        self.signal_augmentation = signal_augmentation
        self.image_augmentation = image_augmentation
        self.num_hypotheses = num_hypotheses
        self.sampling = sampling
        self.seed = int(seed)
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        """Select the epoch whose random draws ``__getitem__`` reproduces."""
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.reader)

    def _rects(self, height: int, width: int, intrinsics: CameraIntrinsics, top: int,
               left: int, flipped: bool, rng: np.random.Generator) -> np.ndarray:
        if self.zone_layout == "calibrated":
            # The returned intrinsics already describe the crop and flip, and the FoV
            # is symmetric, so the projected grid is mirrored (order included) by itself.
            return zone_rects(intrinsics, self.grid, fov_deg=self.fov_deg)
        if self.zone_layout == "training":
            return training_zone_rects(height, width, self.training_grid,
                                       self.training_zone_px, self.training_max_offset_px,
                                       generator=rng)
        rects = self._fixed_rects.copy()
        rects[:, [0, 2]] -= top
        rects[:, [1, 3]] -= left
        if flipped:
            rects = mirror_zone_rects(rects, width, math.isqrt(rects.shape[0]))
        return rects

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        if not -len(self) <= index < len(self):
            raise IndexError(f"item {index} out of range for {len(self)} items")
        index = index % len(self)
        rng = np.random.default_rng((self.seed, self.epoch, index))
        frame = self.reader[index]
        if self.image_augmentation is not None:
            aug = self.image_augmentation.apply(frame.image, frame.depth_m, frame.intrinsics,
                                                rng)
            image, depth, intr = aug.image, aug.depth_m, aug.intrinsics
            top, left, flipped = aug.crop_top, aug.crop_left, aug.flipped
        else:
            image = frame.image.astype(np.float32) / 255.0
            depth, intr = frame.depth_m, frame.intrinsics
            top = left = 0
            flipped = False
        height, width = depth.shape
        rects = self._rects(height, width, intr, top, left, flipped, rng)
        if self.depth_scale_range is not None:
            low, high = np.log(self.depth_scale_range)
            depth = depth * np.float32(np.exp(rng.uniform(low, high)))

        zones = simulate_zones(torch.from_numpy(np.ascontiguousarray(depth)),
                               torch.from_numpy(rects), self.simulator,
                               max_targets=self.max_targets)
        rects = perturb_layout(rects, (height, width), self.layout_jitter_px,
                               self.layout_rotation_deg, rng)
        mean, sigma, valid = zones.mean_m, zones.sigma_m, zones.valid
        if self.signal_augmentation is not None:
            generator = torch.Generator().manual_seed(int(rng.integers(2**62)))
            mean, sigma, valid = self.signal_augmentation(mean, sigma, valid, generator)
        hypotheses = sample_hypotheses(mean, sigma, valid, self.num_hypotheses, self.sampling)
        image_rgb = np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)
        targets = {} if self.max_targets == 1 else {
            "zone_targets": torch.from_numpy(self._target_slots(zones, mean, sigma, valid))}
        return {**targets,
            "image": torch.from_numpy(normalise_image(image, self.image_mean, self.image_std)),
            "image_rgb": torch.from_numpy(image_rgb),
            "depth": torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32))[None],
            "zone_mean_sigma": torch.stack([mean, sigma], dim=-1).to(torch.float32),
            "zone_valid": valid.to(torch.bool),
            "zone_no_target": zones.no_target & ~valid.to(torch.bool),
            "zone_rects": torch.from_numpy(rects.astype(np.float32)),
            "hypotheses": hypotheses.to(torch.float32),
            "intrinsics": torch.tensor([intr.fx, intr.fy, intr.cx, intr.cy],
                                       dtype=torch.float32),
        }

    def _target_slots(self, zones, mean: torch.Tensor, sigma: torch.Tensor,
                      valid: torch.Tensor) -> np.ndarray:
        """(Z, NETWORK_TARGET_SLOTS, 2) float32 network target inputs of the simulated
        zones with their primary readings as augmented (:func:`readings_changed`)."""
        grid = math.isqrt(mean.shape[0])
        simulated = {name: getattr(zones, name).numpy() for name in
                     ("target_mean_m", "target_sigma_m", "target_valid", "target_signal")}
        valid = valid.bool() & (mean > 0)
        changed = readings_changed(simulated, zones.mean_m.numpy(), mean.numpy(),
                                   sigma.numpy(), valid.numpy(), self.simulator.max_range_m)
        frame = ZoneFrame(*(a.numpy().reshape(grid, grid) for a in
                            (mean * valid, sigma * valid, valid)),
                          **{k: v.reshape(grid, grid, -1) for k, v in changed.items()})
        return fixed_target_slots(target_inputs(frame)[None], (1, mean.shape[0]),
                                  NETWORK_TARGET_SLOTS)[0]


def perturb_layout(rects: np.ndarray, image_size: tuple[int, int], max_offset_px: float,
                   max_rotation_deg: float, rng: np.random.Generator) -> np.ndarray:
    """A zone layout as a slightly wrong calibration would place it.

    Every rectangle keeps its size; its centre is rotated about the image centre by one
    angle within +- ``max_rotation_deg`` and shifted by one offset within +-
    ``max_offset_px`` in x and y (the same for all zones, as a calibration error is).

    Args:
        rects: (Z, 4) (y0, x0, y1, x1) in pixels.
        image_size: (H, W) in pixels.
        max_offset_px: largest shift, pixels.
        max_rotation_deg: largest rotation, degrees.
        rng: the random draws.

    Returns:
        (Z, 4) float32 rectangles (the input itself when both limits are 0).
    """
    if max_offset_px == 0 and max_rotation_deg == 0:
        return rects
    angle = np.deg2rad(rng.uniform(-max_rotation_deg, max_rotation_deg))
    shift_y, shift_x = rng.uniform(-max_offset_px, max_offset_px, size=2)
    centre_y, centre_x = (image_size[0] - 1) / 2, (image_size[1] - 1) / 2
    rects = np.asarray(rects, dtype=np.float64)
    cy, cx = (rects[:, 0] + rects[:, 2]) / 2 - centre_y, (rects[:, 1] + rects[:, 3]) / 2 - centre_x
    new_y = centre_y + np.sin(angle) * cx + np.cos(angle) * cy + shift_y
    new_x = centre_x + np.cos(angle) * cx - np.sin(angle) * cy + shift_x
    half_h, half_w = (rects[:, 2] - rects[:, 0]) / 2, (rects[:, 3] - rects[:, 1]) / 2
    return np.stack([new_y - half_h, new_x - half_w, new_y + half_h, new_x + half_w],
                    axis=1).astype(np.float32)


class ZJUL5TrainingDataset(Dataset):
    """Real-zone ZJU-L5 samples as training items (for fine-tuning and validation).

    Hypotheses are sampled from each zone's histogram when the samples carry one
    (histogram sensors, e.g. THDR3K) and ``from_histograms`` is set (the network's
    ``histogram_hypotheses``), else from its measured mean and sigma. The only
    augmentation is an optional horizontal flip (zone rectangles and their order are
    mirrored with the image).

    Args:
        samples: a :class:`~deltar.data.zju_l5.ZJUL5Dataset` or any sequence of samples.
        num_hypotheses: K per zone.
        sampling: ``icdf`` or ``uniform``.
        flip_prob: probability of a horizontal flip.
        seed: base seed; item ``i`` of epoch ``e`` draws from ``(seed, e, i)``.
        image_mean, image_std: per-channel image normalisation (the network's contract).
        with_targets: items also carry ``zone_targets`` (Z, NETWORK_TARGET_SLOTS, 2),
            the sample's own targets (its primary reading alone when it has none).
        from_histograms: draw hypotheses from the samples' histograms where they have
            them.
    """

    def __init__(self, samples: Sequence, num_hypotheses: int = 16, sampling: str = "icdf",
                 flip_prob: float = 0.0, seed: int = 0,
                 image_mean: Sequence[float] = IMAGENET_MEAN,
                 image_std: Sequence[float] = IMAGENET_STD, with_targets: bool = False,
                 from_histograms: bool = False) -> None:
        self.samples, self.num_hypotheses, self.sampling = samples, num_hypotheses, sampling
        self.with_targets, self.from_histograms = bool(with_targets), bool(from_histograms)
        self.flip_prob, self.seed, self.epoch = flip_prob, int(seed), 0
        self.image_mean, self.image_std = tuple(image_mean), tuple(image_std)

    def set_epoch(self, epoch: int) -> None:
        """Select the epoch whose random draws ``__getitem__`` reproduces."""
        self.epoch = int(epoch)

    def __len__(self) -> int:
        return len(self.samples)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        sample = self.samples[index]
        rng = np.random.default_rng((self.seed, self.epoch, index))
        image = sample.rgb.astype(np.float32) / 255.0
        depth, rects = sample.depth_m, sample.zone_rects.copy()
        mean_sigma, valid = sample.zone_mean_sigma.copy(), sample.zone_valid.copy()
        no_target = (np.zeros_like(valid) if sample.zone_no_target is None
                     else sample.zone_no_target.copy())
        counts = sample.hist_counts if self.from_histograms else None
        intr = sample.intrinsics
        targets = (fixed_target_slots(target_inputs(sample.zone_frame())[None],
                                      (1, len(valid)), NETWORK_TARGET_SLOTS)[0]
                   if self.with_targets else None)
        if rng.random() < self.flip_prob:
            width = image.shape[1]
            image, depth = image[:, ::-1], depth[:, ::-1]
            # Mirroring reverses each zone row, so per-zone data are reordered the same way.
            order = np.arange(len(valid)).reshape(sample.grid, sample.grid)[:, ::-1].ravel()
            rects = mirror_zone_rects(rects, width, sample.grid)
            mean_sigma, valid, no_target = mean_sigma[order], valid[order], no_target[order]
            counts = None if counts is None else counts[order]
            targets = None if targets is None else targets[order]
            if intr is not None:
                intr = flip_intrinsics(intr)
        mean_sigma = np.where(valid[:, None], mean_sigma, 0.0).astype(np.float32)
        mean = torch.from_numpy(mean_sigma[:, 0].copy())
        sigma = torch.from_numpy(mean_sigma[:, 1].copy())
        valid_t = torch.from_numpy(valid)
        if counts is not None:
            hypotheses = sample_hypotheses_from_histogram(
                torch.from_numpy(sample.hist_edges_m), torch.from_numpy(counts.copy()),
                valid_t, self.num_hypotheses)
        else:
            hypotheses = sample_hypotheses(mean, sigma, valid_t, self.num_hypotheses,
                                           self.sampling)
        intrinsics = ([intr.fx, intr.fy, intr.cx, intr.cy] if intr is not None
                      else [float("nan")] * 4)
        extra = {} if targets is None else {"zone_targets": torch.from_numpy(targets)}
        return {**extra,
            "image": torch.from_numpy(normalise_image(np.ascontiguousarray(image),
                                                      self.image_mean, self.image_std)),
            "image_rgb": torch.from_numpy(np.ascontiguousarray(
                np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8))),
            "depth": torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32))[None],
            "zone_mean_sigma": torch.from_numpy(mean_sigma),
            "zone_valid": valid_t,
            "zone_no_target": torch.from_numpy(np.ascontiguousarray(no_target)),
            "zone_rects": torch.from_numpy(rects.astype(np.float32)),
            "hypotheses": hypotheses.to(torch.float32),
            "intrinsics": torch.tensor(intrinsics, dtype=torch.float32),
        }


class IndexedConcat(ConcatDataset):
    """Concatenated datasets whose items also carry their global ``index``.

    ``set_epoch`` is forwarded to every part that has it.
    """

    def set_epoch(self, epoch: int) -> None:
        """Forward the epoch to every dataset that draws per-epoch randomness."""
        for dataset in self.datasets:
            if hasattr(dataset, "set_epoch"):
                dataset.set_epoch(epoch)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        item = dict(super().__getitem__(index))
        item["index"] = torch.tensor(int(index), dtype=torch.int64)
        return item
