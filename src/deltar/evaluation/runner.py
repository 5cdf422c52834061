"""The evaluation loop: any number of depth *methods* over a ZJU-L5-layout set.

A method is anything that turns a :class:`~deltar.data.zju_l5.ZJUL5Sample` into an
(H, W) depth map in metres (the :class:`Predictor` protocol). Methods are created by
name from a registry: every classical baseline is registered here, and other packages
add theirs with :func:`register_method` (one name) or :func:`register_method_family`
(a prefix such as ``"model"``, so ``"model:deltar-official"`` calls the family's
factory with ``"deltar-official"``).
"""

from __future__ import annotations

import time
import warnings
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Protocol

import numpy as np

from deltar.evaluation.baselines import BASELINES, run_baseline
from deltar.evaluation.metrics import (
    COVERAGE_KEYS,
    EmptyFrameError,
    MetricAccumulator,
    coverage_metrics,
    depth_metrics,
)
from deltar.sensor.zone_frame import NO_TARGET_DEPTH_M, no_target_as_readings

if TYPE_CHECKING:
    from deltar.data.zju_l5 import ZJUL5Sample


class Predictor(Protocol):
    """A depth method: one sample in, one (H, W) float depth map in metres out.

    A method that also gives a per-pixel sigma returns an object with ``depth_m`` and
    ``uncertainty_m`` ((H, W) metres, e.g. a
    :class:`~deltar.inference.prediction.DepthPrediction`) instead; its sigma is then
    scored too (:func:`~deltar.evaluation.metrics.coverage_metrics`).
    """

    def __call__(self, sample: ZJUL5Sample) -> np.ndarray: ...


#: Suffix of a baseline's variant that reads zones with no target as ``NO_TARGET_DEPTH_M``.
NO_TARGET_SUFFIX = "+far"


@dataclass(frozen=True)
class BaselinePredictor:
    """A classical baseline (:func:`~deltar.evaluation.baselines.run_baseline`) as a method.

    Attributes:
        baseline: name in :data:`~deltar.evaluation.baselines.BASELINES`.
        no_target_depth_m: when set, zones that reported no target (the sample's
            ``zone_no_target``) count as readings at this depth, metres (the
            ``"<baseline>+far"`` methods); None: they are invalid zones, as classically.
    """

    baseline: str
    no_target_depth_m: float | None = None

    def __call__(self, sample: ZJUL5Sample) -> np.ndarray:
        """(H, W) float32 depth in metres from the sample's image and zone means.

        Zones flagged valid but reporting no distance (mean <= 0, which the ZJU-L5 reader
        accepts) carry no measurement, so they are treated as invalid here.
        """
        means = sample.zone_mean_sigma[:, 0]
        valid = sample.zone_valid & (means > 0)
        if self.no_target_depth_m is not None and sample.zone_no_target is not None:
            means, valid = no_target_as_readings(means, valid, sample.zone_no_target,
                                                 self.no_target_depth_m)
        return run_baseline(self.baseline, sample.rgb, means, valid, sample.zone_rects)


def resize_like_release(depth_m: np.ndarray, height: int, width: int, *,
                        min_depth: float | None = None,
                        max_depth: float | None = None) -> np.ndarray:
    """Resize a predicted depth map the way the official evaluation does.

    The release clips the network output to the depth range and resizes it to the input
    size with bilinear interpolation and ``align_corners=True``; a model predictor that
    returns half-resolution depth can use this to match its metrics.

    Args:
        depth_m: (h, w) depth in metres.
        height, width: output size in pixels.
        min_depth, max_depth: the depth range the map is clipped to before resizing,
            metres (the release's are 1e-3 and 10; pass the evaluation's range). None:
            that side is not clipped (the map's own depth, e.g. beyond 10 m for a
            ``--max-depth 20`` evaluation).

    Returns:
        (height, width) float32 depth in metres.
    """
    from deltar.inference.preprocess import resize_to_image

    depth = np.asarray(depth_m, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"depth_m must be an (h, w) array, got shape {depth.shape}")
    if height < 1 or width < 1:
        raise ValueError(f"output size must be positive, got {height}x{width}")
    low = 0.0 if min_depth is None else min_depth
    if (min_depth is not None and not min_depth > 0) or \
            (max_depth is not None and not low < max_depth):
        raise ValueError(f"need 0 < min_depth < max_depth, got min_depth={min_depth}, "
                         f"max_depth={max_depth}")
    if min_depth is not None or max_depth is not None:
        depth = np.clip(depth, None if min_depth is None else np.float32(min_depth),
                        None if max_depth is None else np.float32(max_depth))
    return resize_to_image(depth[None, None], (height, width), align_corners=True)[0, 0]


_METHODS: dict[str, Callable[[], Predictor]] = {}
_FAMILIES: dict[str, Callable[[str], Predictor]] = {}


def register_method(name: str, factory: Callable[[], Predictor], *,
                    overwrite: bool = False) -> None:
    """Make a method available by name (e.g. to ``deltar evaluate --method``).

    Args:
        name: method name; must not contain ``","`` or ``":"`` and must not be ``"all"``.
        factory: called once per evaluation run to build the predictor (load weights
            there, not at registration).
        overwrite: replace an existing registration instead of raising.
    """
    if not name or "," in name or ":" in name or name == "all":
        raise ValueError(f"invalid method name {name!r}")
    if name in _METHODS and not overwrite:
        raise ValueError(f"method {name!r} is already registered")
    _METHODS[name] = factory


def register_method_family(prefix: str, factory: Callable[[str], Predictor], *,
                           overwrite: bool = False) -> None:
    """Make ``"<prefix>:<anything>"`` methods available; ``factory(anything)`` builds them.

    Args:
        prefix: family name, e.g. ``"model"``; no ``","`` or ``":"``.
        factory: builds the predictor from the part after the colon; it should raise
            ``ValueError`` for names it does not know.
        overwrite: replace an existing family instead of raising.
    """
    if not prefix or "," in prefix or ":" in prefix:
        raise ValueError(f"invalid method family prefix {prefix!r}")
    if prefix in _FAMILIES and not overwrite:
        raise ValueError(f"method family {prefix!r} is already registered")
    _FAMILIES[prefix] = factory


def available_methods() -> list[str]:
    """Registered method names, then one ``"<prefix>:NAME"`` entry per family."""
    return [*_METHODS, *(f"{prefix}:NAME" for prefix in _FAMILIES)]


def resolve_method_names(spec: str | Sequence[str]) -> list[str]:
    """Expand a method list such as ``"nearest,bilinear"`` or ``"all"`` (every baseline).

    Args:
        spec: comma-separated names or a sequence of names; ``"all"`` expands to every
            classical baseline.

    Returns:
        Unique names in the given order.

    Raises:
        ValueError: an unknown name (the message lists the valid ones) or an empty list.
    """
    items = spec.split(",") if isinstance(spec, str) else list(spec)
    names: list[str] = []
    for item in (part.strip() for part in items):
        if not item:
            continue
        expanded = list(BASELINES) if item == "all" else [item]
        for name in expanded:
            prefix = name.split(":", 1)[0] if ":" in name else None
            known = name in _METHODS or (prefix in _FAMILIES and name.split(":", 1)[1])
            if not known:
                raise ValueError(f"unknown method {name!r}; valid methods: all, "
                                 f"{', '.join(available_methods())}")
            if name not in names:
                names.append(name)
    if not names:
        raise ValueError("no method given")
    return names


def create_predictor(name: str) -> Predictor:
    """Build the predictor of a registered method (see :func:`resolve_method_names`)."""
    resolve_method_names([name])
    if name in _METHODS:
        return _METHODS[name]()
    prefix, rest = name.split(":", 1)
    return _FAMILIES[prefix](rest)


for _baseline in BASELINES:
    register_method(_baseline, lambda baseline=_baseline: BaselinePredictor(baseline))
for _baseline in BASELINES:
    register_method(_baseline + NO_TARGET_SUFFIX, lambda baseline=_baseline: BaselinePredictor(
        baseline, NO_TARGET_DEPTH_M))


@dataclass
class EvaluationResult:
    """Outcome of :func:`evaluate_methods`.

    Attributes:
        metrics: method name -> averaged metrics (keys of ``METRIC_KEYS``, and of
            ``COVERAGE_KEYS`` for methods that give a sigma).
        frames: frames evaluated per method (frames with valid ground truth).
        skipped: frames skipped for lack of valid ground truth.
        refused: ``(frame name, reason)`` of the frames left out with ``keep_going``
            (zones that cannot be a real reading, or a method refused the frame).
        seconds_per_frame: method name -> mean prediction time in seconds.
    """

    metrics: dict[str, dict[str, float]] = field(default_factory=dict)
    frames: int = 0
    skipped: int = 0
    refused: list[tuple[str, str]] = field(default_factory=list)
    seconds_per_frame: dict[str, float] = field(default_factory=dict)


FrameCallback = Callable[[int, "ZJUL5Sample", Mapping[str, np.ndarray]], None]


def check_sample_zones(sample: ZJUL5Sample, source: str | None = None) -> None:
    """Refuse a frame whose zone reading is physically impossible (before scoring it).

    The checks of :meth:`~deltar.sensor.zone_frame.ZoneFrame.physical_error` (valid
    zones beyond the sensor's range, sigmas larger than it, empty histograms), and valid
    zones whose rectangles all lie outside the image: the model methods refuse such a
    frame, so every method does (a baseline would score a constant map).

    Args:
        sample: the frame.
        source: its file, for the message.

    Raises:
        ValueError: ``"frame '<name>' (<source>): <problem>"``.
    """
    from deltar.sensor.geometry import check_zones_in_image

    where = f"frame {sample.name!r}" + ("" if source is None else f" ({source})")
    try:
        problem = sample.zone_frame().physical_error()
    except ValueError as err:
        problem = str(err)
    if problem is not None:
        raise ValueError(f"{where}: {problem}")
    # The estimator's check, on the zones it takes as readings (ZJUL5Sample.zone_frame);
    # a frame partly outside is left to the model methods to warn of, once.
    valid = np.asarray(sample.zone_valid, dtype=bool) & (sample.zone_mean_sigma[:, 0] > 0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        check_zones_in_image(sample.zone_rects, valid, sample.rgb.shape[:2], where)


def _predict_frame(sample: ZJUL5Sample, predictors: Mapping[str, Predictor]
                   ) -> tuple[dict[str, np.ndarray], dict[str, np.ndarray], dict[str, float]]:
    """Every method's depth (and sigma, where it gives one) of one frame, metres, and
    its prediction time, seconds.

    Raises:
        ValueError: a method refuses the frame or returns a map of the wrong shape or
            with NaN / inf; the message names the method and frame.
    """
    predictions: dict[str, np.ndarray] = {}
    sigmas: dict[str, np.ndarray] = {}
    seconds: dict[str, float] = {}
    for name, predictor in predictors.items():
        start = time.perf_counter()
        try:
            output = predictor(sample)
        except ValueError as err:
            raise ValueError(f"method {name!r}, frame {sample.name!r}: {err}") from err
        seconds[name] = time.perf_counter() - start
        if hasattr(output, "uncertainty_m"):
            sigmas[name] = np.asarray(output.uncertainty_m)
        depth = np.asarray(getattr(output, "depth_m", output))
        if depth.shape != sample.depth_m.shape:
            raise ValueError(f"method {name!r} returned shape {depth.shape} for frame "
                             f"{sample.name!r}, expected {sample.depth_m.shape}")
        if not np.all(np.isfinite(depth)):
            raise ValueError(f"method {name!r} returned NaN or inf for frame "
                             f"{sample.name!r}")
        predictions[name] = depth
    return predictions, sigmas, seconds


def evaluate_methods(
    samples: Sequence[ZJUL5Sample],
    predictors: Mapping[str, Predictor],
    *,
    min_depth: float = 1e-3,
    max_depth: float = 10.0,
    limit: int | None = None,
    on_frame: FrameCallback | None = None,
    keep_going: bool = False,
) -> EvaluationResult:
    """Run every method on every frame and average the metrics per frame, then over frames.

    Args:
        samples: the frames (e.g. a :class:`~deltar.data.zju_l5.ZJUL5Dataset`).
        predictors: method name -> predictor.
        min_depth, max_depth: ground-truth range in metres (see ``depth_metrics``).
        limit: evaluate only the first ``limit`` frames.
        on_frame: called after each frame with (index, sample, {method: depth}), e.g. to
            save visualisations or advance a progress bar ({} for a frame left out).
        keep_going: a frame that would raise (its zones, or a method refusing it) is left
            out for every method, with a warning, and listed in ``result.refused``, so that
            every method is scored on the same frames.

    Returns:
        An :class:`EvaluationResult`.

    Raises:
        ValueError: a frame's zones cannot be a real reading (:func:`check_sample_zones`),
            a method refuses a frame or returns a map of the wrong shape or with NaN /
            inf (the message names the method and frame; without ``keep_going``), or no
            frame has valid ground truth.
    """
    if not predictors:
        raise ValueError("predictors is empty")
    if limit is not None and limit < 1:
        raise ValueError(f"limit must be >= 1, got {limit}")
    count = len(samples) if limit is None else min(limit, len(samples))
    accumulators = {name: MetricAccumulator(min_depth, max_depth) for name in predictors}
    coverages: dict[str, MetricAccumulator] = {}
    seconds = dict.fromkeys(predictors, 0.0)
    result = EvaluationResult()
    for index in range(count):
        sample = samples[index]
        # The file holding the zone reading, from sets that list their files.
        files = samples.frame_files(index) if hasattr(samples, "frame_files") else None
        try:
            check_sample_zones(sample, None if not files else str(files[0]))
            predictions, sigmas, frame_seconds = _predict_frame(sample, predictors)
        except ValueError as err:
            if not keep_going:
                raise
            warnings.warn(f"leaving out frame {sample.name!r}: {err}", RuntimeWarning,
                          stacklevel=2)
            result.refused.append((sample.name, str(err)))
            if on_frame is not None:
                on_frame(index, sample, {})
            continue
        for name, spent in frame_seconds.items():
            seconds[name] += spent
        try:
            frame_metrics = {name: depth_metrics(depth, sample.depth_m, min_depth, max_depth)
                             for name, depth in predictions.items()}
            frame_coverage = {name: coverage_metrics(predictions[name], sigma, sample.depth_m,
                                                     min_depth, max_depth)
                              for name, sigma in sigmas.items()}
        except EmptyFrameError as err:
            warnings.warn(f"skipping frame {sample.name!r}: {err}", RuntimeWarning,
                          stacklevel=2)
            result.skipped += 1
        else:
            for name, values in frame_metrics.items():
                accumulators[name].add(values)
            for name, values in frame_coverage.items():
                coverages.setdefault(name, MetricAccumulator(min_depth, max_depth,
                                                             COVERAGE_KEYS)).add(values)
            result.frames += 1
        if on_frame is not None:
            on_frame(index, sample, predictions)
    if len(result.refused) == count:
        raise ValueError(f"all {count} frames were left out (first: {result.refused[0][1]})")
    if result.frames == 0:
        raise ValueError(f"none of the {count} frames has ground truth inside "
                         f"({min_depth}, {max_depth}) m")
    result.metrics = {name: acc.compute() for name, acc in accumulators.items()}
    for name, acc in coverages.items():
        result.metrics[name].update(acc.compute())
    predicted = count - len(result.refused)
    result.seconds_per_frame = {name: total / predicted for name, total in seconds.items()}
    return result
