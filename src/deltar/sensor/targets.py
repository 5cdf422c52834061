"""Every target of a zone as the network reads it: distances and shares of the zone.

A zone that reports several targets (:attr:`~deltar.sensor.zone_frame.ZoneFrame.target_mean_m`)
sees several surfaces. The plane-select network offers each as a hypothesis and weighs
it by the share of the zone's footprint it covers. The sensor does not report that
share, but it reports each target's signal; a return's signal falls with the square of
its distance, so with equal reflectance a target's share of the footprint is
proportional to ``signal * distance^2``. Without signals every reported target gets an
equal share.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from deltar.sensor.zone_frame import ZoneFrame

__all__ = ["NETWORK_TARGET_SLOTS", "fixed_target_slots", "readings_changed",
           "stacked_target_inputs", "target_inputs"]

#: Targets per zone the network reads: the primary reading and the largest other one
#: (a zone rarely reports a third: benchmarks/RESULTS.md, several targets per zone
#: through the network; a third slot would cost the head half as much work again).
NETWORK_TARGET_SLOTS = 2


def target_inputs(frame: ZoneFrame) -> np.ndarray:
    """(Z, T, 2) float32 ``[distance (metres), share]`` per zone and target slot.

    Slot 0 is the zone's primary reading (``frame.mean_m``; share 1 when the zone
    reports nothing else); slots 1.. are the zone's other valid targets, largest share
    first (the frame's order on ties). Empty slots and invalid zones are 0. Shares are
    ``signal * distance^2`` normalised over the zone's targets when the frame carries
    target signals (``target_signal``), else equal. A frame with one target per zone
    gives T = 1.
    """
    primary_m, _, primary_valid = frame.flat()
    if frame.target_mean_m is None:  # one target per zone: the primary readings alone
        single = np.zeros((frame.zone_count, 1, 2), dtype=np.float32)
        single[:, 0, 0] = np.where(primary_valid, primary_m, 0.0)
        single[:, 0, 1] = primary_valid
        return single
    mean, _, valid = frame.flat_targets()
    zones, slots = mean.shape
    out = np.zeros((zones, slots, 2), dtype=np.float32)
    out[:, 0, 0] = np.where(primary_valid, primary_m, 0.0)
    signal = frame.target_signal
    # The primary is the target that lies at the primary reading (slot 0 in the
    # default, strongest-first order; anywhere in closest-first order).
    is_primary = valid & primary_valid[:, None] & (
        np.abs(mean - primary_m[:, None]) <= 1e-4 * np.maximum(primary_m[:, None], 1.0))
    first = np.argmax(is_primary, axis=1)
    found = is_primary.any(axis=1)
    weight = np.where(valid, 1.0, 0.0) if signal is None else np.where(
        valid, np.maximum(signal.reshape(zones, -1), 0.0) * mean.astype(np.float64) ** 2, 0.0)
    weight[~primary_valid] = 0.0
    primary_weight = np.where(found, weight[np.arange(zones), first],
                              np.where(primary_valid, 1.0, 0.0))
    # The other valid targets of valid zones, largest share first (the frame's order on
    # ties), so that keeping the first slots keeps the largest targets.
    other = valid & primary_valid[:, None] & ~(found[:, None] & (
        np.arange(slots)[None, :] == first[:, None]))
    order = np.argsort(np.where(other, -weight, np.inf), axis=1, kind="stable")[:, : slots - 1]
    kept = np.take_along_axis(other, order, axis=1)
    out[:, 1:, 0] = np.where(kept, np.take_along_axis(mean, order, axis=1), 0.0)
    out[:, 1:, 1] = np.where(kept, np.take_along_axis(weight, order, axis=1), 0.0)
    total = primary_weight + out[:, 1:, 1].sum(axis=1)
    out[:, 0, 1] = primary_weight
    has_weight = total > 0
    out[has_weight, :, 1] /= total[has_weight, None]
    out[primary_valid & ~has_weight, 0, 1] = 1.0
    return out


def stacked_target_inputs(frames: Sequence[ZoneFrame], slots: int | None = None
                          ) -> np.ndarray:
    """(B, Z, T, 2) float32 :func:`target_inputs` of a batch.

    Args:
        frames: the batch's zone frames.
        slots: T, fixed (an exported network's input; missing targets are 0, further
            ones dropped, the smallest first); None: the most targets any zone of the
            batch reports, at most :data:`NETWORK_TARGET_SLOTS` (1 when no zone reports
            a second).
    """
    parts = [target_inputs(frame) for frame in frames]
    if slots is None:
        used = max(int((part[..., 0] > 0).sum(axis=1).max(initial=1)) for part in parts)
        slots = min(used, NETWORK_TARGET_SLOTS)
    return np.concatenate([fixed_target_slots(part[None], (1, part.shape[0]), slots)
                           for part in parts])


def fixed_target_slots(zone_targets: np.ndarray | None, batch_zones: tuple[int, int],
                       slots: int) -> np.ndarray:
    """(B, Z, slots, 2) float32: ``zone_targets`` (B, Z, T, 2) padded with empty slots or
    cut (the slots come largest share first); all 0 when None, which reads as no further
    target.

    Raises:
        ValueError: ``zone_targets`` not (B, Z, T, 2) for the batch's (B, Z).
    """
    out = np.zeros((*batch_zones, slots, 2), dtype=np.float32)
    if zone_targets is None:
        return out
    targets = np.asarray(zone_targets, dtype=np.float32)
    if targets.ndim != 4 or targets.shape[:2] != tuple(batch_zones) or targets.shape[3] != 2:
        raise ValueError(f"zone_targets must be (B, Z, T, 2) with (B, Z) = {batch_zones}, got "
                         f"{targets.shape}")
    used = min(slots, targets.shape[2])
    out[:, :, :used] = targets[:, :, :used]
    return out


def readings_changed(targets: dict[str, np.ndarray], before_mean_m: np.ndarray,
                     mean_m: np.ndarray, sigma_m: np.ndarray, valid: np.ndarray,
                     max_range_m: float) -> dict[str, np.ndarray]:
    """A zone's targets after its primary reading was changed (a bias, a dropped zone):
    what the degraded sets and the training items report.

    A zone's change scales all its targets (a bias in the timing moves every return); a
    zone that became invalid loses them all; a target scaled past the sensor's range is
    not reported. Target 0 becomes the changed primary reading.

    Args:
        targets: ``target_mean_m``, ``target_sigma_m`` (metres), ``target_valid`` (bool)
            and ``target_signal`` (Z, T) arrays of the zones as simulated.
        before_mean_m: (Z,) primary readings as simulated, metres.
        mean_m, sigma_m, valid: (Z,) the changed primary readings (metres) and validity.
        max_range_m: the sensor's range, metres.

    Returns:
        The four (Z, T) arrays, changed (new arrays; float32 distances).
    """
    mean, sigma = np.asarray(mean_m, np.float32), np.asarray(sigma_m, np.float32)
    valid = np.asarray(valid, bool)
    before = np.asarray(before_mean_m, np.float64)
    factor = np.where(before > 0, mean / np.maximum(before, 1e-6), 0.0)
    scaled = targets["target_mean_m"] * factor[:, None]
    keep = valid[:, None] & targets["target_valid"] & (scaled <= max_range_m)
    out = {"target_valid": keep,
           "target_mean_m": np.where(keep, scaled, 0.0).astype(np.float32),
           "target_sigma_m": np.where(keep, targets["target_sigma_m"] * factor[:, None],
                                      0.0).astype(np.float32),
           "target_signal": np.where(keep, targets["target_signal"], 0.0)}
    out["target_mean_m"][:, 0] = np.where(valid, mean, 0.0)
    out["target_sigma_m"][:, 0] = np.where(valid, sigma, 0.0)
    out["target_valid"][:, 0] = valid
    return out
