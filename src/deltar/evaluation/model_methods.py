"""Learned models as evaluation methods: ``model:NAME|PATH`` and ``official:PATH``.

``model:default`` is the bundled model, ``model:runs/x/model.pt`` any deltar checkpoint,
``official:nyu.pt`` the officially released weights, ``onnx:model.onnx`` an exported
(float32 or int8) model run by onnxruntime (``onnx:default`` the bundled model's shipped
export). A ``+flip`` suffix
(``model:default+flip``) adds test-time flip averaging (not for ``onnx:``); a ``+network``
suffix (``model:default+network``, also ``onnx:x.onnx+network``) scores the network
alone, without the estimator's confidence blend with the colorization fill
(:mod:`deltar.inference.blend`, on by default for plane-select networks). Each is loaded
by :func:`~deltar.inference.loading.load_estimator` and runs through
:class:`~deltar.inference.estimator.DepthEstimator` with the sample's own zone
rectangles, at the network input size the one size rule gives for the sample's image
(:func:`deltar.inference.preprocess.network_input_size`: aspect kept, the design
size's pixel budget, multiples of 32; an ONNX file at its exported size), exactly as
``deltar predict`` runs it, and its output is resized to the ground truth's resolution
(``official:`` with the release's own final resize, ``align_corners=True``).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from deltar.evaluation.runner import register_method_family

if TYPE_CHECKING:
    from deltar.data.zju_l5 import ZJUL5Sample
    from deltar.inference.estimator import DepthEstimator
    from deltar.inference.prediction import DepthPrediction


class EstimatorPredictor:
    """Evaluation method wrapping a :class:`DepthEstimator`.

    Args:
        estimator: the estimator (:meth:`DepthEstimator.network_size_for` gives the
            network resolution).
    """

    def __init__(self, estimator: DepthEstimator) -> None:
        self.estimator = estimator

    def __call__(self, sample: ZJUL5Sample) -> DepthPrediction:
        """The estimator's prediction (depth and sigma, (H, W) metres) for one sample.

        Hypotheses come from the sample's histogram when it has one (histogram
        sensors, e.g. THDR3K) and the weights were trained on histograms
        (``histogram_hypotheses``), else from each zone's mean and sigma. Zones flagged valid
        but reporting no distance (mean <= 0) are treated as invalid, as the classical
        baselines treat them.
        """
        return self.estimator.predict(sample.rgb, sample.zone_frame(),
                                      zone_rects=sample.zone_rects)


#: Method-name suffix asking for test-time flip averaging.
FLIP_SUFFIX = "+flip"
#: Method-name suffix asking for the network's depth without the confidence blend.
NETWORK_SUFFIX = "+network"
#: Method-name suffix asking the estimator not to infer no-target flags for samples
#: without them (docs/inference.md, "Zones without no-target flags").
UNINFERRED_SUFFIX = "+uninferred"
#: Method-name suffix asking the estimator to keep every zone, without the outlier rule
#: the weights carry (:mod:`deltar.sensor.zone_outliers`).
KEPT_SUFFIX = "+kept"


def _split_suffixes(name: str) -> tuple[str, dict[str, object]]:
    """(name, estimator keyword arguments) from ``+flip`` / ``+network`` /
    ``+uninferred`` / ``+kept`` suffixes."""
    options: dict[str, object] = {}
    while True:
        if name.endswith(FLIP_SUFFIX):
            name, options["flip_average"] = name[: -len(FLIP_SUFFIX)], True
        elif name.endswith(NETWORK_SUFFIX):
            name, options["blend"] = name[: -len(NETWORK_SUFFIX)], None
        elif name.endswith(UNINFERRED_SUFFIX):
            name = name[: -len(UNINFERRED_SUFFIX)]
            options["no_target_min_neighbour_m"] = None
        elif name.endswith(KEPT_SUFFIX):
            name, options["zone_outliers"] = name[: -len(KEPT_SUFFIX)], None
        else:
            return name, options


def checkpoint_predictor(name_or_path: str) -> EstimatorPredictor:
    """``model:NAME|PATH[+flip][+network][+uninferred][+kept]``: a bundled model name or a deltar
    checkpoint."""
    from deltar.inference.loading import load_estimator

    name_or_path, options = _split_suffixes(name_or_path)
    return EstimatorPredictor(load_estimator(name_or_path, kind="checkpoint", **options))


def official_predictor(path: str) -> EstimatorPredictor:
    """``official:PATH[+flip][+network]``: the released weights (e.g. ``nyu.pt``), design
    480x640 (not plane-select, so never blended: ``+network`` changes nothing), their
    outputs resized as the release's evaluation resizes them
    (``DepthEstimator(output_align_corners=True)``, as ``load_estimator`` builds them)."""
    from deltar.inference.loading import load_estimator

    path, options = _split_suffixes(path)
    return EstimatorPredictor(load_estimator(path, kind="official", **options))


def onnx_predictor(path: str) -> EstimatorPredictor:
    """``onnx:PATH[+network][+uninferred][+kept]``: an exported ONNX model (``deltar export``,
    also ``--int8``), or ``onnx:default``, the bundled model's shipped export.

    It runs at its fixed input size; the sample's zone layout must fit the one it was
    exported for (else ``ValueError``; export with that layout).
    """
    from deltar.inference.checks import check_backend_options
    from deltar.inference.loading import load_estimator

    path, options = _split_suffixes(path)
    # Refused before the file is read, naming the method's suffix.
    check_backend_options("float32", bool(options.get("flip_average")), True,
                          names=("precision", f"onnx:{path}: +flip"))
    return EstimatorPredictor(load_estimator(path, kind="onnx", **options))


def method_input_files(name: str) -> list[Path]:
    """The existing files a ``model:`` / ``onnx:`` / ``official:`` method reads (an ONNX
    file's ``.data`` weights too): inputs no output of the evaluation may replace. None
    for other methods or a bundled name."""
    prefix, _, rest = name.partition(":")
    if prefix not in ("model", "onnx", "official") or not rest:
        return []
    path = Path(_split_suffixes(rest)[0])
    files = [path, path.with_name(path.name + ".data")] if prefix == "onnx" else [path]
    return [file for file in files if file.exists()]


register_method_family("model", checkpoint_predictor)
register_method_family("onnx", onnx_predictor)
register_method_family("official", official_predictor)
