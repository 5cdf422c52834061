"""Depth metrics, flat-wall (plane) metrics, classical baselines and the evaluation loop."""

from deltar.evaluation.baselines import BASELINES, DEFAULT_FALLBACK_DEPTH_M, run_baseline
from deltar.evaluation.metrics import (
    METRIC_KEYS,
    EmptyFrameError,
    MetricAccumulator,
    depth_metrics,
)
from deltar.evaluation.plane import Plane, PlaneMetrics, fit_plane, plane_metrics
from deltar.evaluation.runner import (
    BaselinePredictor,
    EvaluationResult,
    Predictor,
    available_methods,
    create_predictor,
    evaluate_methods,
    register_method,
    register_method_family,
    resize_like_release,
    resolve_method_names,
)

__all__ = [
    "BASELINES",
    "DEFAULT_FALLBACK_DEPTH_M",
    "METRIC_KEYS",
    "BaselinePredictor",
    "EmptyFrameError",
    "EvaluationResult",
    "MetricAccumulator",
    "Plane",
    "PlaneMetrics",
    "Predictor",
    "available_methods",
    "create_predictor",
    "depth_metrics",
    "evaluate_methods",
    "fit_plane",
    "plane_metrics",
    "register_method",
    "register_method_family",
    "resize_like_release",
    "resolve_method_names",
    "run_baseline",
]

# Registers the "model:" and "official:" method families (learned models).
from deltar.evaluation import model_methods  # noqa: F401
