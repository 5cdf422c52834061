"""Training / evaluation samples with a simulated L5 signal, from any RGB-D reader.

For every item: read the frame, optionally augment the image (crop, rotation, flip,
colour), place the zones on the final image, simulate the zone readings from its depth
(``deltar.sensor.simulate``), optionally augment the signal (drop zones, noisy means) and
sample the depth hypotheses the network consumes. All randomness of item ``i`` in epoch
``e`` comes from ``(seed, e, i)``, so a run is reproducible whatever the worker layout.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
import torch
from torch.utils.data import Dataset

from deltar.calibration.camera import CameraIntrinsics
from deltar.data.rgbd import RGBDFrame
from deltar.data.transforms import ImageAugmentation, mirror_zone_rects, normalize_image
from deltar.sensor.augment import SignalAugmentation, training_zone_rects
from deltar.sensor.geometry import DEFAULT_FOV_DEG, zone_rects
from deltar.sensor.sampling import sample_hypotheses
from deltar.sensor.simulate import SimulatorConfig, simulate_zones

#: Named zone layouts; a (Z, 4) array of fixed rectangles is accepted as well.
ZONE_LAYOUTS: tuple[str, ...] = ("calibrated", "training")


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

    Items are dicts of tensors: ``image`` (3, H, W) float32 ImageNet-normalised,
    ``image_rgb`` (H, W, 3) uint8, ``depth`` (1, H, W) float32 metres (0 invalid),
    ``zone_mean_sigma`` (Z, 2) float32 metres, ``zone_valid`` (Z,) bool, ``zone_rects``
    (Z, 4) float32 pixels, ``hypotheses`` (Z, K) float32 metres, ``intrinsics`` (4,) float32
    fx, fy, cx, cy in pixels of the returned image.
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
    ) -> None:
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

        zones = simulate_zones(torch.from_numpy(np.ascontiguousarray(depth)),
                               torch.from_numpy(rects), self.simulator)
        mean, sigma, valid = zones.mean_m, zones.sigma_m, zones.valid
        if self.signal_augmentation is not None:
            generator = torch.Generator().manual_seed(int(rng.integers(2**62)))
            mean, sigma, valid = self.signal_augmentation(mean, sigma, valid, generator)
        hypotheses = sample_hypotheses(mean, sigma, valid, self.num_hypotheses, self.sampling)
        image_rgb = np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)
        return {
            "image": torch.from_numpy(normalize_image(image)),
            "image_rgb": torch.from_numpy(image_rgb),
            "depth": torch.from_numpy(np.ascontiguousarray(depth, dtype=np.float32))[None],
            "zone_mean_sigma": torch.stack([mean, sigma], dim=-1).to(torch.float32),
            "zone_valid": valid.to(torch.bool),
            "zone_rects": torch.from_numpy(rects.astype(np.float32)),
            "hypotheses": hypotheses.to(torch.float32),
            "intrinsics": torch.tensor([intr.fx, intr.fy, intr.cx, intr.cy],
                                       dtype=torch.float32),
        }
