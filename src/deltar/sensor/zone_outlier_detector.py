"""A learned detector of biased zones: a small network on each zone's neighbourhood.

The rule of :mod:`deltar.sensor.zone_outliers` sets a zone aside only when it lies
beyond *every* valid neighbour. A biased zone with one farther neighbour (another
biased zone, or a real farther surface) escapes it: on the simulated degraded frames of
ten indoor scenes it caught 15 % of the zones biased by 10-20 % and 31 % of those biased
by 20-40 % (benchmarks/RESULTS.md). The detector here reads more of the neighbourhood
(:data:`ZONE_FEATURE_NAMES`: the spread of the log differences to the eight
neighbours, the same in units of the zones' own sigmas, the difference to the median of
the 5 x 5 neighbourhood, the zone's relative sigma, depth and target count) and gives
each valid zone a probability of being biased by more than 5 %, from a two-layer
perceptron (:class:`OutlierDetector`).

It learns from frames whose zones are right (:func:`fit_outlier_detector`): each frame
is degraded in the process as ``deltar simulate --drop-fraction/--bias-prob`` does
(:class:`~deltar.sensor.augment.SignalAugmentation`), so which zones were biased, and by
how much, is known. Whether the estimator uses it, and at which probability, is chosen
with the rest of the output stage on frames of the training scenes, among candidates
that include the rule and no rejection at all
(:func:`deltar.evaluation.uncertainty.fit_outlier_rule`); it travels with the weights
(``config["zone_outlier_rule"]``).
"""

from __future__ import annotations

import itertools
import math
import numbers
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from deltar.sensor.zone_frame import ZoneFrame
from deltar.sensor.zone_values import NEIGHBOURS_3x3, zone_neighbours

__all__ = ["ZONE_FEATURE_NAMES", "OutlierDetector", "fit_outlier_detector",
           "zone_outlier_features"]

#: The per-zone inputs of :class:`OutlierDetector`, in order (log = natural log of metres).
ZONE_FEATURE_NAMES = (
    "valid_neighbours",            # valid zones among the eight neighbours, 0-8
    "nearest_log_difference",      # min over neighbours of log(zone) - log(neighbour)
    "farthest_log_difference",     # max of the same
    "median_log_difference",       # median of the same
    "median_sigma_difference",     # median of (zone - neighbour) / hypot(sigmas, 1 cm)
    "lowest_sigma_difference",     # min of the same
    "fraction_nearer",             # neighbours more than 3 % nearer than the zone, fraction
    "log_difference_to_median_5x5",  # log(zone) - median log of its 24 neighbours (5 x 5)
    "relative_sigma",              # sigma / mean
    "log_distance",                # log(mean / 1 m)
    "targets",                     # valid targets the zone reports (1 for a single-target frame)
)
#: A zone counts as biased, in the detector's training, when its reading moved by more
#: than this in log distance (about 5 %).
BIAS_LOG_THRESHOLD = 0.05
#: Margin, in log distance, below which a neighbour does not count as nearer.
_NEARER_MARGIN = 0.03
_NEIGHBOURS_5x5_RING_FIRST = NEIGHBOURS_3x3 + tuple(
    (dy, dx) for dy in range(-2, 3) for dx in range(-2, 3) if max(abs(dy), abs(dx)) == 2)


def _median_over_known(values: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Median along axis 0 of ``values`` where ``known`` (as ``np.nanmedian``), 0 where
    nothing is known; much cheaper than ``nanmedian`` on these small stacks."""
    ordered = np.sort(np.where(known, values, np.inf), axis=0)  # unknown last
    count = known.sum(axis=0)
    rows, cols = np.indices(count.shape)
    low = ordered[np.maximum(count - 1, 0) // 2, rows, cols]
    high = ordered[np.maximum(count, 1) // 2, rows, cols]
    return np.where(count > 0, (low + high) / 2, 0.0)


def zone_outlier_features(mean_m: np.ndarray, sigma_m: np.ndarray, valid: np.ndarray,
                          target_count: np.ndarray | None = None) -> np.ndarray:
    """Each zone's :data:`ZONE_FEATURE_NAMES`, from its reading and its neighbours'.

    Args:
        mean_m: (n, n) zone readings in metres (ignored where not valid).
        sigma_m: (n, n) zone sigmas in metres.
        valid: (n, n) bool validity.
        target_count: (n, n) valid targets per zone; None: 1 everywhere.

    Returns:
        (n, n, F) float64 features; entries of invalid zones are meaningless. Statistics
        over no valid neighbour are 0.

    Raises:
        ValueError: arrays that are not (n, n) alike.
    """
    valid = np.asarray(valid, dtype=bool)
    mean = np.asarray(mean_m, dtype=np.float64)
    sigma = np.asarray(sigma_m, dtype=np.float64)
    count = np.ones(valid.shape) if target_count is None \
        else np.asarray(target_count, dtype=np.float64)
    if valid.ndim != 2 or valid.shape[0] != valid.shape[1] or \
            any(a.shape != valid.shape for a in (mean, sigma, count)):
        raise ValueError(f"mean_m, sigma_m, valid and target_count must all be (n, n), got "
                         f"{mean.shape}, {sigma.shape}, {valid.shape}, {count.shape}")
    # A reading that is not a finite positive distance cannot be judged: left out.
    valid = valid & np.isfinite(mean) & (mean > 0) & np.isfinite(sigma)
    safe_mean = np.where(valid, np.maximum(mean, 1e-6), 1.0)
    log_mean = np.where(valid, np.log(safe_mean), np.nan)
    # One stack of the 24 zones around each (5 x 5); its first eight are the 3 x 3 ring.
    wide = zone_neighbours(log_mean, _NEIGHBOURS_5x5_RING_FIRST)
    difference = log_mean[None] - wide[:8]  # NaN where a neighbour or the zone is missing
    known = ~np.isnan(difference)
    valid_neighbours = known.sum(axis=0)
    some = valid_neighbours > 0
    neighbour_metres = zone_neighbours(np.where(valid, mean, np.nan), NEIGHBOURS_3x3)
    own_sigma = np.where(valid, sigma, 0.0)
    neighbour_sigma = zone_neighbours(np.where(valid, sigma, np.nan), NEIGHBOURS_3x3)
    # The 1 cm floor keeps two sharp readings of one wall from reading as far apart.
    in_sigmas = (safe_mean[None] - neighbour_metres) / np.sqrt(
        own_sigma[None] ** 2 + neighbour_sigma ** 2 + 1e-4)
    filled = np.where(known, difference, 0.0)
    wide_known = ~np.isnan(wide)
    features = np.stack([
        valid_neighbours.astype(np.float64),
        np.where(some, np.where(known, difference, np.inf).min(axis=0), 0.0),
        np.where(some, np.where(known, difference, -np.inf).max(axis=0), 0.0),
        _median_over_known(difference, known),
        _median_over_known(in_sigmas, known),
        np.where(some, np.where(known, in_sigmas, np.inf).min(axis=0), 0.0),
        (filled > _NEARER_MARGIN).sum(axis=0) / np.maximum(valid_neighbours, 1),
        np.where(wide_known.any(axis=0) & valid,
                 log_mean - _median_over_known(wide, wide_known), 0.0),
        own_sigma / safe_mean,  # 0 where not valid
        np.where(valid, log_mean, 0.0),
        count,
    ], axis=-1)
    return np.nan_to_num(features, nan=0.0, posinf=0.0, neginf=0.0)


def _frame_features(frame: ZoneFrame) -> np.ndarray:
    """(n, n, F) :func:`zone_outlier_features` of a frame (its targets counted)."""
    count = None if frame.target_valid is None else frame.target_valid.sum(axis=-1)
    return zone_outlier_features(frame.mean_m, frame.sigma_m, frame.valid, count)


@dataclass(frozen=True, eq=False)
class OutlierDetector:
    """A two-layer perceptron giving each valid zone the probability that its reading is
    biased (module docstring); zones above ``threshold`` are set aside.

    Attributes:
        feature_mean, feature_scale: (F,) standardisation of :data:`ZONE_FEATURE_NAMES`.
        layers: ((weight (F, H1), bias (H1,)), (weight (H1, H2), bias (H2,)),
            (weight (H2, 1), bias (1,))), ReLU between them, a logistic at the end.
        threshold: probability above which a zone is set aside, in (0, 1).
    """

    feature_mean: np.ndarray
    feature_scale: np.ndarray
    layers: tuple[tuple[np.ndarray, np.ndarray], ...]
    threshold: float = 0.5

    def __post_init__(self) -> None:
        size = len(ZONE_FEATURE_NAMES)
        mean = np.array(self.feature_mean, dtype=np.float64)
        scale = np.array(self.feature_scale, dtype=np.float64)
        if mean.shape != (size,) or scale.shape != (size,) or not np.all(scale > 0) or \
                not (np.all(np.isfinite(mean)) and np.all(np.isfinite(scale))):
            raise ValueError(f"outlier detector feature_mean and feature_scale must be "
                             f"({size},) finite (scale > 0), got {mean.shape} and "
                             f"{scale.shape}")
        layers = []
        width = size
        for index, pair in enumerate(self.layers):
            weight, bias = (np.array(a, dtype=np.float64) for a in pair)
            if weight.ndim != 2 or weight.shape[0] != width or bias.shape != \
                    (weight.shape[1],) or not (np.all(np.isfinite(weight)) and
                                               np.all(np.isfinite(bias))):
                raise ValueError(f"outlier detector layer {index}: weight must be ({width}, "
                                 f"k) and bias (k,), finite, got {weight.shape} and "
                                 f"{bias.shape}")
            layers.append((weight, bias))
            width = weight.shape[1]
        if not layers or width != 1:
            raise ValueError("outlier detector layers must end in one output")
        threshold = self.threshold
        if isinstance(threshold, bool) or not isinstance(threshold, numbers.Real) or \
                not 0.0 < threshold < 1.0:
            raise ValueError(f"outlier detector threshold must be a probability in (0, 1), "
                             f"got {threshold!r}")
        # Own, read-only copies: the detector is hashed on them.
        for array in (mean, scale, *(a for pair in layers for a in pair)):
            array.setflags(write=False)
        object.__setattr__(self, "feature_mean", mean)
        object.__setattr__(self, "feature_scale", scale)
        object.__setattr__(self, "layers", tuple(layers))
        object.__setattr__(self, "threshold", float(threshold))

    def _key(self) -> tuple:
        arrays = (self.feature_mean, self.feature_scale,
                  *(a for pair in self.layers for a in pair))
        return (self.threshold, *((a.shape, a.tobytes()) for a in arrays))

    def __eq__(self, other: object) -> bool:
        """Same weights and threshold (arrays compared exactly)."""
        return isinstance(other, OutlierDetector) and self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

    def logit(self, features: np.ndarray) -> np.ndarray:
        """(..., F) features -> (...) logit of being biased."""
        hidden = (np.asarray(features, dtype=np.float64) - self.feature_mean) \
            / self.feature_scale
        for index, (weight, bias) in enumerate(self.layers):
            hidden = hidden @ weight + bias
            if index < len(self.layers) - 1:
                np.maximum(hidden, 0.0, out=hidden)
        return hidden[..., 0]

    def probability(self, frame: ZoneFrame) -> np.ndarray:
        """(n, n) probability that each zone's reading is biased (0 at invalid zones)."""
        logit = np.clip(self.logit(_frame_features(frame)), -60.0, 60.0)
        return np.where(frame.valid, 1.0 / (1.0 + np.exp(-logit)), 0.0)

    def find(self, frame: ZoneFrame) -> np.ndarray:
        """(n, n) bool, the valid zones whose probability is above ``threshold``."""
        return self.probability(frame) > self.threshold

    def with_threshold(self, threshold: float) -> OutlierDetector:
        """The same detector at another threshold."""
        return OutlierDetector(self.feature_mean, self.feature_scale, self.layers, threshold)

    def to_dict(self) -> dict[str, Any]:
        """The detector as a JSON-ready dict (a checkpoint's ``config["zone_outlier_rule"]``)."""
        return {"detector": "zone_mlp", "threshold": self.threshold,
                "feature_mean": self.feature_mean.tolist(),
                "feature_scale": self.feature_scale.tolist(),
                "layers": [{"weight": w.tolist(), "bias": b.tolist()} for w, b in self.layers]}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> OutlierDetector:
        """Read :meth:`to_dict`'s form.

        Raises:
            ValueError: missing or unknown keys, or bad values (the message says which).
        """
        keys = {"detector", "threshold", "feature_mean", "feature_scale", "layers"}
        if not isinstance(data, Mapping) or set(data) != keys or \
                data["detector"] != "zone_mlp":
            raise ValueError(f"a zone outlier detector needs exactly the keys "
                             f"{sorted(keys)} with detector 'zone_mlp', got "
                             f"{sorted(data) if isinstance(data, Mapping) else data!r}")
        layers = data["layers"]
        if not isinstance(layers, Sequence) or not all(
                isinstance(layer, Mapping) and set(layer) == {"weight", "bias"}
                for layer in layers):
            raise ValueError("zone outlier detector layers must be a list of "
                             "{'weight', 'bias'} dicts")
        try:
            return cls(np.asarray(data["feature_mean"], dtype=np.float64),
                       np.asarray(data["feature_scale"], dtype=np.float64),
                       tuple((np.asarray(layer["weight"], dtype=np.float64),
                              np.asarray(layer["bias"], dtype=np.float64))
                             for layer in layers), data["threshold"])
        except (TypeError, ValueError) as err:
            raise ValueError(f"zone outlier detector does not read: {err}") from err


def fit_outlier_detector(frames: Sequence[ZoneFrame], *, drop_fraction: float = 0.2,
                         bias_prob: float = 0.3, bias_mean_m: float = 0.10,
                         bias_std_m: float = 0.15, draws: int = 4, hidden: int = 32,
                         weight_decay: float = 1e-4, seed: int = 0,
                         threshold: float = 0.5) -> OutlierDetector:
    """Train an :class:`OutlierDetector` on frames whose zones are right.

    Each frame is used as it is (no zone biased) and ``draws`` times degraded as
    ``deltar simulate --drop-fraction --bias-prob --bias-mean --bias-std`` degrades a
    set: a zone of a degraded copy is a positive when its reading moved by more than
    :data:`BIAS_LOG_THRESHOLD` in log distance. The perceptron minimises the mean
    logistic loss plus ``weight_decay`` times its squared weights, by L-BFGS from a
    seeded start, so the same frames and seed give the same detector.

    Args:
        frames: zone frames of the training scenes, clean (a zone already biased would
            be learnt as right).
        drop_fraction, bias_prob: fraction of valid zones dropped, probability that a
            remaining zone is biased.
        bias_mean_m, bias_std_m: the bias's mean and standard deviation, metres.
        draws: degraded copies of each frame.
        hidden: units of each hidden layer.
        weight_decay: L2 weight on the weights (not the biases).
        seed: seed of the degradations and of the start.
        threshold: the returned detector's threshold.

    Returns:
        The detector.

    Raises:
        ValueError: no frame, bad counts, or frames whose degraded copies bias no zone.
    """
    import torch  # the degradation's generator; fitting runs where the network does

    from deltar.sensor.augment import SignalAugmentation

    if not frames:
        raise ValueError("fit_outlier_detector needs at least one frame")
    for name, value in (("draws", draws), ("hidden", hidden)):
        if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
            raise ValueError(f"{name} must be an integer >= 1, got {value!r}")
    if not (isinstance(weight_decay, numbers.Real) and math.isfinite(weight_decay)
            and weight_decay >= 0):
        raise ValueError(f"weight_decay must be a finite number >= 0, got {weight_decay!r}")
    if isinstance(threshold, bool) or not isinstance(threshold, numbers.Real) or \
            not 0.0 < threshold < 1.0:
        raise ValueError(f"threshold must be a probability in (0, 1), got {threshold!r}")
    augmentation = SignalAugmentation(drop_fraction, bias_prob, bias_mean_m, bias_std_m)
    generator = torch.Generator().manual_seed(seed)
    features, labels = [], []
    for frame in frames:
        features.append(_frame_features(frame)[frame.valid])
        labels.append(np.zeros(int(frame.valid.sum())))
        for _ in range(draws):
            mean, sigma, valid = (t.numpy().reshape(frame.valid.shape) for t in augmentation(
                torch.from_numpy(frame.mean_m.reshape(-1).astype(np.float64)),
                torch.from_numpy(frame.sigma_m.reshape(-1).astype(np.float64)),
                torch.from_numpy(frame.valid.reshape(-1)), generator))
            count = None if frame.target_valid is None else \
                np.where(valid, frame.target_valid.sum(axis=-1), 0)
            moved = np.abs(np.log(np.maximum(mean, 1e-6) / np.maximum(frame.mean_m, 1e-6)))
            features.append(zone_outlier_features(mean, sigma, valid, count)[valid])
            labels.append((moved[valid] > BIAS_LOG_THRESHOLD).astype(np.float64))
    inputs, targets = np.concatenate(features), np.concatenate(labels)
    if not 0 < targets.sum() < targets.size:
        raise ValueError("the frames' degraded copies give no biased zone (or only biased "
                         "ones): give more frames or a larger bias_prob")
    feature_mean = inputs.mean(axis=0)
    feature_scale = np.where(inputs.std(axis=0) > 1e-9, inputs.std(axis=0), 1.0)
    layers = _train_perceptron((inputs - feature_mean) / feature_scale, targets, hidden,
                               weight_decay, np.random.default_rng(seed))
    return OutlierDetector(feature_mean, feature_scale, layers, threshold)


def _train_perceptron(inputs: np.ndarray, targets: np.ndarray, hidden: int,
                      weight_decay: float, rng: np.random.Generator
                      ) -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """Two ReLU layers of ``hidden`` units and a logistic output, fitted by L-BFGS."""
    from scipy.optimize import minimize  # scipy: on use
    from scipy.special import expit

    sizes = [inputs.shape[1], hidden, hidden, 1]
    shapes = list(itertools.pairwise(sizes))

    def unpack(theta: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
        layers, at = [], 0
        for a, b in shapes:
            weight = theta[at:at + a * b].reshape(a, b)
            at += a * b
            layers.append((weight, theta[at:at + b]))
            at += b
        return layers

    def loss(theta: np.ndarray) -> tuple[float, np.ndarray]:
        layers = unpack(theta)
        activations = [inputs]
        for index, (weight, bias) in enumerate(layers):
            out = activations[-1] @ weight + bias
            activations.append(np.maximum(out, 0.0) if index < len(layers) - 1 else out)
        logit = activations[-1][:, 0]
        value = np.mean(np.logaddexp(0.0, logit) - targets * logit) + weight_decay * sum(
            float(np.sum(w * w)) for w, _ in layers)
        delta = ((expit(logit) - targets) / targets.size)[:, None]
        grads = []
        for index in range(len(layers) - 1, -1, -1):
            weight, _ = layers[index]
            grads.append((activations[index].T @ delta + 2.0 * weight_decay * weight,
                          delta.sum(axis=0)))
            if index:
                delta = (delta @ weight.T) * (activations[index] > 0)
        flat = [g.ravel() for pair in reversed(grads) for g in pair]
        return float(value), np.concatenate(flat)

    start = np.concatenate([part for a, b in shapes for part in (
        rng.normal(0.0, math.sqrt(2.0 / a), a * b), np.zeros(b))])
    theta = minimize(loss, start, jac=True, method="L-BFGS-B",
                     options={"maxiter": 500}).x
    return tuple((w.copy(), b.copy()) for w, b in unpack(theta))
