"""ST's compact normalised histograms (CNH) as zone-frame histograms.

The histogram parts (VL53L7CH, VL53L8CH) can report, per zone, a short histogram of
the returned light (``cnh_data``) beside the usual distance and sigma. Its bins are
cut from the device's own histogram by three numbers the driver is configured with
(``vl53lmz_cnh_init_config``): the first device bin ``start_bin``, the number of CNH
bins ``num_bins`` and ``sub_sample``, the device bins summed into one CNH bin. CNH bin
``k`` therefore covers device bins ``start_bin + k * sub_sample`` up to
``start_bin + (k + 1) * sub_sample``; one device bin spans ``device_bin_m`` of
distance (about 37.5 mm: :data:`DEVICE_BIN_M`).

A CNH reading becomes a :class:`~deltar.sensor.zone_frame.ZoneFrame` whose
``hist_counts`` are the bin values with negative values (ambient subtracted by the
sensor) clipped to 0 and each zone normalised to sum 1, and whose ``hist_edges_m``
are the bin edges above. :func:`simulate_cnh` makes the same kind of histogram from a
metric depth map, for training models for these sensors.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from deltar.sensor.zone_frame import Orientation, ZoneFrame
from deltar.sensor.zone_values import (
    DEFAULT_VALID_STATUS,
    NO_TARGET_STATUS,
    number_array,
    valid_status_codes,
)

#: Distance spanned by one bin of the device histogram, metres. Not given in ST's
#: public driver headers; this is the value public VL53L8CH host code uses
#: (37.5348 mm), in line with the "about 37.5 mm" quoted on ST's community forum.
#: Pass ``device_bin_m`` to :class:`CNHConfig` if your documentation says otherwise.
DEVICE_BIN_M = 0.0375348


@dataclass(frozen=True)
class CNHConfig:
    """The CNH bin configuration the driver reports (``vl53lmz_cnh_init_config``).

    The defaults (``start_bin`` 0, 18 bins, ``sub_sample`` 7) are those of ST's CNH
    example configuration: 18 bins of about 26 cm covering 0 to 4.73 m.

    Attributes:
        start_bin: first device-histogram bin (>= 0).
        num_bins: number of CNH bins (>= 1).
        sub_sample: device bins summed into one CNH bin (>= 1).
        device_bin_m: distance spanned by one device bin, metres.
    """

    start_bin: int = 0
    num_bins: int = 18
    sub_sample: int = 7
    device_bin_m: float = DEVICE_BIN_M

    def __post_init__(self) -> None:
        for name, low in (("start_bin", 0), ("num_bins", 1), ("sub_sample", 1)):
            value = getattr(self, name)
            if int(value) != value or value < low:
                raise ValueError(f"CNHConfig.{name} must be an integer >= {low}, got {value!r}")
            object.__setattr__(self, name, int(value))
        if not (math.isfinite(self.device_bin_m) and self.device_bin_m > 0):
            raise ValueError(f"CNHConfig.device_bin_m must be > 0 metres, got "
                             f"{self.device_bin_m!r}")

    @property
    def bin_width_m(self) -> float:
        """Width of one CNH bin, metres."""
        return self.sub_sample * self.device_bin_m

    @property
    def range_m(self) -> tuple[float, float]:
        """(near, far) distance covered by the CNH bins, metres."""
        edges = self.edges_m()
        return float(edges[0]), float(edges[-1])

    def edges_m(self) -> np.ndarray:
        """(num_bins + 1,) float64 bin edges in metres, increasing."""
        device_bins = self.start_bin + self.sub_sample * np.arange(self.num_bins + 1)
        return device_bins * self.device_bin_m

    @classmethod
    def from_range(cls, near_m: float, far_m: float, num_bins: int,
                   device_bin_m: float = DEVICE_BIN_M) -> CNHConfig:
        """The configuration whose ``num_bins`` bins cover ``[near_m, far_m]``.

        ``start_bin`` and ``sub_sample`` are whole device bins, so the covered range is
        the requested one widened to device bins: the near end rounded down, the bin
        width rounded up to a whole number of device bins.

        Raises:
            ValueError: ``far_m <= near_m``, a negative ``near_m`` or ``num_bins < 1``.
        """
        if not (math.isfinite(near_m) and math.isfinite(far_m) and 0 <= near_m < far_m):
            raise ValueError(f"CNH range must satisfy 0 <= near < far metres, got "
                             f"{near_m}..{far_m}")
        if int(num_bins) != num_bins or num_bins < 1:
            raise ValueError(f"num_bins must be an integer >= 1, got {num_bins!r}")
        start = math.floor(near_m / device_bin_m + 1e-9)
        width = (far_m - start * device_bin_m) / (num_bins * device_bin_m)
        return cls(start, int(num_bins), max(1, math.ceil(width - 1e-9)), device_bin_m)

    def to_dict(self) -> dict:
        """JSON-ready dict (``start_bin``, ``num_bins``, ``sub_sample``, ``device_bin_m``)."""
        return {"start_bin": self.start_bin, "num_bins": self.num_bins,
                "sub_sample": self.sub_sample, "device_bin_m": self.device_bin_m}


def normalize_cnh(bin_values: np.ndarray | Sequence, zones: int, num_bins: int,
                  source: str = "cnh bin_values") -> np.ndarray:
    """Clip negative CNH values to 0 and normalise each zone's histogram to sum 1.

    Args:
        bin_values: (Z, B) or flat (Z * B,) bin values, zone-major (driver order).
        zones: Z, 16 or 64.
        num_bins: B, CNH bins per zone.
        source: name used in error messages.

    Returns:
        (Z, B) float32; a zone with no positive value stays all zero.

    Raises:
        ValueError: wrong number of values, NaN or infinite values.
    """
    try:
        values = np.asarray(bin_values, dtype=np.float64)
    except (TypeError, ValueError) as err:
        raise ValueError(f"{source} must be numbers: {err}") from err
    if values.size != zones * num_bins:
        raise ValueError(f"{source} has {values.size} values with shape {values.shape}; "
                         f"expected {zones} zones x {num_bins} bins")
    values = values.reshape(zones, num_bins)
    if not np.all(np.isfinite(values)):
        raise ValueError(f"{source} has NaN or infinite values in zones "
                         f"{np.flatnonzero(~np.isfinite(values).all(1)).tolist()}")
    values = np.clip(values, 0.0, None)
    total = values.sum(1, keepdims=True)
    return np.where(total > 0, values / np.where(total > 0, total, 1.0), 0.0).astype(
        np.float32)


def zone_frame_from_cnh(distance_mm: Sequence[float], bin_values: np.ndarray | Sequence, *,
                        config: CNHConfig | None = None,
                        range_sigma_mm: Sequence[float] | None = None,
                        target_status: Sequence[int] | None = None,
                        nb_target_detected: Sequence[int] | None = None,
                        valid_status: Sequence[int] = DEFAULT_VALID_STATUS,
                        orientation: Orientation | None = None,
                        timestamp_s: float | None = None,
                        sensor_model: str = "VL53L8CH") -> ZoneFrame:
    """A zone frame with a histogram from a CNH reading (driver order, flat lists).

    A zone is valid when its distance is positive and finite, its histogram has mass,
    and, where given, ``nb_target_detected`` is > 0 (the sensor does not clear stale
    distances of zones without a target) and ``target_status`` is in ``valid_status``.
    Without ``range_sigma_mm``, sigma is the spread of the histogram's strongest run
    of non-empty bins (see :func:`histogram_sigma_m`). Zones with
    ``nb_target_detected == 0`` or status 255 report *no target* (``frame.no_target``).

    Args:
        distance_mm: Z = 16 or 64 distances in millimetres.
        bin_values: (Z, B) or flat (Z * B,) CNH bin values.
        config: the CNH bin configuration; ``CNHConfig()`` (18 bins) when None.
        range_sigma_mm: optional Z sigmas in millimetres.
        target_status: optional Z ST target status codes.
        nb_target_detected: optional Z target counts.
        valid_status: status codes counted as valid.
        orientation: how the driver grid maps onto the image (identity by default).
        timestamp_s: capture time in seconds.
        sensor_model: free text stored with the frame.

    Returns:
        A :class:`ZoneFrame` with ``hist_counts`` (n, n, B), normalised per zone, and
        ``hist_edges_m`` (B + 1,); mean and sigma in metres, zero where invalid.

    Raises:
        ValueError: wrong lengths or non-finite values, naming the field.
    """
    cfg = config or CNHConfig()
    distance = _flat("distance_mm", distance_mm)
    zones = distance.size
    n = math.isqrt(zones)
    if n * n != zones or n not in (4, 8):
        raise ValueError(f"distance_mm has {zones} zones; expected 16 (4x4) or 64 (8x8)")
    hist = normalize_cnh(bin_values, zones, cfg.num_bins)
    mean = distance / 1000.0
    valid = np.isfinite(mean) & (mean > 0) & (hist.sum(1) > 0)
    no_target = None
    if nb_target_detected is not None:
        detected = _flat("nb_target_detected", nb_target_detected, zones) > 0
        valid &= detected
        no_target = ~detected  # the sensor saw nothing within its range there
    status = None
    if target_status is not None:
        codes = _flat("target_status", target_status, zones)
        if np.any((codes < 0) | (codes > 255)):
            raise ValueError("target_status must hold integer codes in 0..255")
        status = codes.astype(np.uint8)
        valid &= np.isin(status, valid_status_codes(valid_status))
        from_status = status == NO_TARGET_STATUS
        no_target = from_status if no_target is None else no_target | from_status
    edges = cfg.edges_m()
    if range_sigma_mm is not None:
        sigma = _flat("range_sigma_mm", range_sigma_mm, zones) / 1000.0
        valid &= np.isfinite(sigma) & (sigma >= 0)
    else:
        sigma = histogram_sigma_m(hist, edges)
    orient = orientation or Orientation()
    grids = [orient.apply(a.reshape(n, n)) for a in (mean, sigma, valid)]
    mean_g, sigma_g, valid_g = grids
    status_g = None if status is None else orient.apply(status.reshape(n, n))
    hist_g = orient.apply(hist.reshape(n, n, cfg.num_bins))
    no_target_g = None if no_target is None else \
        orient.apply(no_target.reshape(n, n)) & ~valid_g
    return ZoneFrame(mean_m=np.where(valid_g, mean_g, 0.0),
                     sigma_m=np.where(valid_g, sigma_g, 0.0), valid=valid_g,
                     status=status_g, hist_edges_m=edges.astype(np.float32),
                     hist_counts=hist_g, timestamp_s=timestamp_s, sensor_model=sensor_model,
                     no_target=no_target_g)


def histogram_sigma_m(counts: np.ndarray, edges_m: np.ndarray) -> np.ndarray:
    """Per-zone spread of a histogram: the standard deviation of its strongest run.

    The strongest run is the run of consecutive non-empty bins with the largest total
    (as in the zone simulator); its count-weighted population standard deviation of
    bin centres is returned. A run of one bin gives ``bin width / sqrt(12)`` (the
    spread of a uniform bin) rather than 0.

    Args:
        counts: (Z, B) non-negative counts.
        edges_m: (B + 1,) bin edges in metres.

    Returns:
        (Z,) float64 metres; 0 for zones without counts.
    """
    from deltar.sensor.simulate_frame import strongest_run  # numpy: no PyTorch needed

    weights = strongest_run(np.asarray(counts, dtype=np.float64))
    edges = np.asarray(edges_m, dtype=np.float64)
    centres = (edges[1:] + edges[:-1]) / 2
    widths = np.diff(edges)
    total = weights.sum(1)
    safe = np.where(total > 0, total, 1.0)
    mean = (weights * centres).sum(1) / safe
    # Within-bin spread (uniform over each bin) plus the spread of the bin centres.
    variance = (weights * ((centres - mean[:, None]) ** 2 + widths ** 2 / 12)).sum(1) / safe
    return np.where(total > 0, np.sqrt(variance), 0.0)


def simulate_cnh(depth_m: np.ndarray, rects: np.ndarray,
                 config: CNHConfig | None = None) -> np.ndarray:
    """CNH-like histograms from a metric depth map: the zones' depth distributions.

    Each zone's pixels are counted in the CNH bins (depth outside the bins' range is
    not counted), then every zone is normalised to sum 1 like the sensor's CNH. The
    result is the ideal, noise-free histogram: no ambient light, no pulse blur.

    Args:
        depth_m: (H, W) depth in metres, 0 = invalid pixel.
        rects: (Z, 4) zone rectangles (y0, x0, y1, x1) in pixels.
        config: the CNH bin configuration; ``CNHConfig()`` when None.

    Returns:
        (Z, num_bins) float32 histograms, each summing to 1 (all zero for a zone with
        no pixel in range).
    """
    import torch

    from deltar.sensor.simulator_config import SimulatorConfig
    from deltar.sensor.zone_histograms import zone_histograms

    cfg = config or CNHConfig()
    depth = np.asarray(depth_m, dtype=np.float32)
    boxes = np.asarray(rects, dtype=np.float32)
    if depth.ndim != 2 or boxes.ndim != 2 or boxes.shape[1] != 4:
        raise ValueError(f"depth_m must be (H, W) and rects (Z, 4), got {depth.shape} and "
                         f"{boxes.shape}")
    device_bins = cfg.start_bin + cfg.num_bins * cfg.sub_sample
    # Histogram over whole device bins from 0, then sum groups of sub_sample bins.
    sim = SimulatorConfig(bin_width_m=cfg.device_bin_m,
                          max_range_m=device_bins * cfg.device_bin_m, ignored_bins=0)
    counts = zone_histograms(torch.from_numpy(depth)[None], torch.from_numpy(boxes)[None],
                             sim)[0].numpy()
    grouped = counts[:, cfg.start_bin:].reshape(boxes.shape[0], cfg.num_bins, cfg.sub_sample)
    return normalize_cnh(grouped.sum(-1), boxes.shape[0], cfg.num_bins, "simulated CNH")


def _flat(name: str, values, count: int | None = None) -> np.ndarray:
    # Numbers stay numbers: strings ("1500") and booleans are refused, never converted.
    if not isinstance(values, np.ndarray | list | tuple):
        values = np.asarray(values)
    arr = number_array(values, name)
    if count is not None and arr.size != count:
        raise ValueError(f"{name} has {arr.size} entries; expected {count}")
    return arr
