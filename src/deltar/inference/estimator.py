"""From an RGB image and a zone frame to a full-resolution depth map: ``DepthEstimator``.

The estimator runs the pipeline around the network: it places the zones in the image
(from a :class:`~deltar.calibration.rig.RigCalibration`, or the nominal geometry of
:mod:`deltar.sensor.placement`), samples the per-zone depth hypotheses, prepares the
network input by the one size rule of :mod:`deltar.inference.preprocess` (which also
maps the zone rectangles into the network input and the output back), runs the network
(PyTorch, optionally flip-averaged by :mod:`deltar.inference.flip`, or onnxruntime via
:mod:`deltar.inference.onnx_runtime`) and returns depth and uncertainty at the input
resolution, through the output stage (:mod:`deltar.inference.output_stage`).

An estimator is built from a loaded model; :func:`deltar.inference.loading.load_estimator`
is the one factory that loads any model source (bundled name, checkpoint, released
weights, ONNX file, preset) and builds it. The estimator reads the weights' input
contract (normalisation, hypothesis sampling and count, design size) from the model's
config (checkpoints: :mod:`deltar.models.checkpoint`) or the ONNX file's metadata.
"""

from __future__ import annotations

import copy
import math
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

from deltar.camera import ZJU_L5_INTRINSICS, CameraIntrinsics
from deltar.contract import HYPOTHESIS_SAMPLINGS, IMAGENET_MEAN, IMAGENET_STD, as_switch
from deltar.inference import checks
from deltar.inference.blend import ConfidenceBlend, resolve_blend
from deltar.inference.fill_schedule import (
    fill_beside_network,
    start_frame_fills,
)
from deltar.inference.output_stage import apply_output_stage
from deltar.inference.prediction import DepthPrediction
from deltar.inference.preprocess import (
    network_input_size,
    normalise_images,
    resize_to_image,
    scale_rects,
)
from deltar.inference.uncertainty import UncertaintyCalibration, resolve_uncertainty
from deltar.inference.zone_consistency import resolve_zone_consistency
from deltar.sensor.geometry import DEFAULT_FOV_DEG, check_zones_in_image
from deltar.sensor.hypotheses import frame_hypotheses
from deltar.sensor.no_target import check_min_neighbour_m, frame_no_target
from deltar.sensor.placement import nominal_zone_rects
from deltar.sensor.targets import stacked_target_inputs
from deltar.sensor.zone_frame import ZoneFrame
from deltar.sensor.zone_outlier_detector import OutlierDetector
from deltar.sensor.zone_outliers import OutlierRule, reject_outlier_zones, resolve_outlier_rule

if TYPE_CHECKING:
    from concurrent.futures import Future

    from deltar.calibration.rig import RigCalibration
    from deltar.inference.onnx_runtime import OnnxDepthModel
    from deltar.models import DeltarNet

__all__ = ["DepthEstimator"]


class DepthEstimator:
    """Dense metric depth from an RGB image and a multi-zone ToF frame.

    Load one with :func:`~deltar.inference.loading.load_estimator` (any model source:
    ``load_estimator("default")``), or build one around a model object you hold, then
    call :meth:`predict`.

    Args:
        model: a ``DeltarNet`` (PyTorch backend), or None with ``onnx_model``; it is put
            in eval mode and moved to ``device`` / ``precision`` in place.
        onnx_model: an :class:`~deltar.inference.onnx_runtime.OnnxDepthModel`
            (onnxruntime backend).
        device: torch device for the PyTorch backend, e.g. ``"cpu"`` or ``"cuda"``.
        precision: ``"float32"``, ``"float16"`` or ``"bfloat16"`` (PyTorch backend).
        input_size: fixed (H, W) network input size in pixels (multiples of 32), which
            every image is resized to whatever its aspect; by default the one size rule
            (:func:`~deltar.inference.preprocess.network_input_size`: each image keeps
            its aspect, scaled to the model's design-size pixel budget, sides rounded
            to multiples of 32). An ONNX model runs at its exported sizes
            (``onnx_model.input_sizes``; the bundled one has the common camera aspects'):
            each image at the size the rule gives it when that size was exported (as
            PyTorch runs it), else stretched to the exported size nearest in aspect, with
            a ``UserWarning`` (when the file records the weights' design size, as the
            bundled one does; without it the rule cannot be applied and the nearest
            aspect is taken silently).
        intrinsics: nominal camera intrinsics used without a calibration (scaled to
            each image); the ZJU-L5 RealSense camera by default.
        fov_deg: sensor field of view for the nominal zone placement, degrees.
        sampling: how hypotheses are drawn from N(mean, sigma) ("icdf" or
            "uniform"); None: the one the weights were trained with
            (``model.network_config.inputs.hypothesis_sampling``, or the ONNX file's metadata).
        histogram_hypotheses: draw the hypotheses of frames with per-zone histograms
            (CNH) from them; None: as the weights were trained (their input contract's
            ``histogram_hypotheses``, False for weights that do not say).
        weights: free text saying where the weights come from (shown by the CLI).
        fold_batch_norms: apply every inference optimisation in place
            (:func:`~deltar.models.optimize.prepare_for_inference`: batch norms folded,
            channels-last, "same" convolutions without a padding copy; outputs change
            only by float rounding, the release's parity holds, tested). Pass False to
            keep a model you will go on training.
        flip_average: test-time augmentation: also run the mirrored image with the
            mirrored zones and average the two depths (twice the time; PyTorch only).
        max_range_m: largest distance a valid zone may read, metres; by default each
            frame's sensor model's range (4 m for the VL53L5CX/L8CX, see
            :data:`~deltar.sensor.zone_values.SENSOR_MAX_RANGE_M`).
        blend: blend the network's depth with the colorization fill of the zones where
            the network is unsure (:class:`~deltar.inference.blend.ConfidenceBlend`;
            lower RMSE on rooms the model never saw; its fill runs on a worker thread
            while the network does): ``"auto"`` (default) does so for plane-select
            networks (``head == "plane_select"``, e.g. the bundled ``default``) with the
            coefficients the weights carry (``config["confidence_blend"]``, fitted with
            ``deltar fit-uncertainty``) or :data:`~deltar.inference.blend.DEFAULT_BLEND`,
            not for other networks; a ``ConfidenceBlend`` always; None never (fastest).
        uncertainty: how ``uncertainty_m`` is computed
            (:class:`~deltar.inference.uncertainty.UncertaintyCalibration`): ``"auto"``
            (default) the calibration the weights carry (``config[
            "uncertainty_calibration"]``, fitted with ``deltar fit-uncertainty``), else
            the network's raw spread; a calibration always; None the raw spread.
        no_target_min_neighbour_m: for frames without no-target flags (e.g. ZJU-L5
            files): ``"auto"`` (default) reads invalid zones as no target by the rule
            the weights carry (``config["no_target_min_neighbour_m"]``, fitted with
            ``deltar fit-uncertainty``; :func:`~deltar.sensor.no_target.infer_no_target`),
            a number of metres uses that threshold, None reads none so.
        zone_outliers: set aside zones that disagree with their neighbours
            (:mod:`deltar.sensor.zone_outliers`): ``"auto"`` (default) by the rule or
            detector the weights carry (``config["zone_outlier_rule"]``), an
            ``OutlierRule`` or ``OutlierDetector``, or None.
        zone_consistency: in [0, 1], how far the depth moves to reproduce the zones'
            readings (:mod:`deltar.inference.zone_consistency`); None: as the weights say.
        output_align_corners: resize the outputs to the image as the released DELTAR
            code does (``align_corners=True``; ``load_estimator`` sets it for the
            released weights), not as OpenCV does (:func:`resize_to_image`).
    """

    def __init__(self, model: DeltarNet | None = None, *,
                 onnx_model: OnnxDepthModel | None = None, device: str = "cpu",
                 precision: str = "float32", input_size: tuple[int, int] | None = None,
                 intrinsics: CameraIntrinsics = ZJU_L5_INTRINSICS,
                 fov_deg: tuple[float, float] = DEFAULT_FOV_DEG, sampling: str | None = None,
                 histogram_hypotheses: bool | None = None,
                 weights: str = "unknown", fold_batch_norms: bool = True,
                 flip_average: bool = False, max_range_m: float | None = None,
                 blend: ConfidenceBlend | str | None = "auto",
                 uncertainty: UncertaintyCalibration | str | None = "auto",
                 no_target_min_neighbour_m: float | str | None = "auto",
                 zone_outliers: OutlierRule | OutlierDetector | str | None = "auto",
                 zone_consistency: float | None = None,
                 output_align_corners: bool = False) -> None:
        if (model is None) == (onnx_model is None):
            raise ValueError("give exactly one of model (PyTorch) or onnx_model (onnxruntime)")
        checks.check_backend_options(precision, flip_average, onnx_model is not None)
        if sampling is not None and sampling not in HYPOTHESIS_SAMPLINGS:
            raise ValueError(f"sampling must be one of {HYPOTHESIS_SAMPLINGS}, got "
                             f"{sampling!r}")
        input_size = checks.resolve_input_size(input_size, onnx_model)
        # The PyTorch backend's device and dtype; an ONNX model runs without torch.
        self.device = self.dtype = None
        if model is not None:
            import torch

            self.device = torch.device(device)
            self.dtype = getattr(torch, precision)
        self.precision = precision
        self.input_size = input_size
        self.intrinsics = intrinsics
        self.fov_deg = checks.check_fov_deg(fov_deg)
        self.weights = weights
        self.flip_average, self.output_align_corners = flip_average, bool(output_align_corners)
        if max_range_m is not None and not (math.isfinite(max_range_m) and max_range_m > 0):
            raise ValueError(f"max_range_m must be a positive number of metres, got "
                             f"{max_range_m!r}")
        self.max_range_m = max_range_m
        self.onnx_model = onnx_model
        self.model = None
        if model is not None:
            model.eval()
            if fold_batch_norms:
                from deltar.models.optimize import prepare_for_inference

                prepare_for_inference(model)
            self.model = model.to(device=self.device, dtype=self.dtype)
        contract = model.contract() if model is not None else onnx_model.contract
        # For an ONNX model the size rule picks among the exported sizes (network_size_for).
        self.design_size = (tuple(contract["design_size"])
                            if contract.get("design_size") is not None else None)
        # The input contract travels with the weights: hypotheses and normalisation.
        self.num_hypotheses = int(contract["num_hypotheses"])
        self.sampling = sampling or contract.get("hypothesis_sampling", "icdf")
        self.histogram_hypotheses = as_switch("histogram_hypotheses", contract.get(
            "histogram_hypotheses", False) if histogram_hypotheses is None
            else histogram_hypotheses)
        self.image_mean = tuple(contract.get("image_mean", IMAGENET_MEAN))
        self.image_std = tuple(contract.get("image_std", IMAGENET_STD))
        self.blend = resolve_blend(blend, contract)
        self.uncertainty = resolve_uncertainty(uncertainty, contract)
        # No-target zones join the fill at the depth the network reads them at.
        far = contract.get("no_target_depth")
        self.no_target_depth_m = None if far is None else float(far)
        self.no_target_min_neighbour_m = check_min_neighbour_m(
            contract.get("no_target_min_neighbour_m") if no_target_min_neighbour_m == "auto"
            else no_target_min_neighbour_m, "no_target_min_neighbour_m")
        self.zone_outliers = resolve_outlier_rule(zone_outliers, contract)
        self.zone_consistency = resolve_zone_consistency(zone_consistency, contract)

    # ------------------------------------------------------------------ prediction
    def network_size_for(self, image_size: tuple[int, int]) -> tuple[int, int]:
        """(h, w) network input size in pixels for images of ``image_size`` (H, W).

        The fixed ``input_size`` (or an ONNX model's one exported size) when set, else
        the one size rule (:func:`~deltar.inference.preprocess.network_input_size`) with
        the model's design size; for an ONNX model exported at several sizes, the rule's
        size when it is one of them, else the exported size nearest in aspect.
        """
        if self.input_size is not None:
            return self.input_size
        rule = network_input_size(*image_size, design_size=self.design_size)
        if self.onnx_model is None or rule in self.onnx_model.input_sizes:
            return rule
        aspect = math.log(image_size[0] / image_size[1])
        return min(self.onnx_model.input_sizes,
                   key=lambda size: (abs(math.log(size[0] / size[1]) - aspect),
                                     -size[0] * size[1]))

    def zone_rects_for(self, frame: ZoneFrame, image_size: tuple[int, int],
                       calibration: RigCalibration | None = None) -> np.ndarray:
        """Zone rectangles (Z, 4) in pixels of an image of ``image_size`` (H, W).

        Uses the calibration when given (its resolution must match the image), else
        the nominal geometry (see :func:`nominal_zone_rects`).
        """
        height, width = image_size
        if calibration is not None:
            return calibration.zone_rects_for(frame, (height, width))
        return nominal_zone_rects(frame, height, width, self.intrinsics, self.fov_deg)

    def image_intrinsics(self, image_size: tuple[int, int],
                         calibration: RigCalibration | None = None) -> CameraIntrinsics:
        """Intrinsics of an image of ``image_size`` (H, W): calibrated or nominal."""
        if calibration is not None:
            return calibration.intrinsics
        return self.intrinsics.scaled(*image_size)

    def hypotheses_for(self, frame: ZoneFrame) -> np.ndarray:
        """(Z, K) float32 depth hypotheses in metres for one frame (zeros where invalid):
        from its histograms when it has them and the weights were trained so
        (``histogram_hypotheses``), else from N(mean, sigma)
        (:func:`~deltar.sensor.hypotheses.frame_hypotheses`, numpy for both backends)."""
        return frame_hypotheses(frame, self.num_hypotheses, self.sampling,
                                self.histogram_hypotheses)

    def prepare(self, images: Sequence[np.ndarray], frames: Sequence[ZoneFrame],
                calibration: RigCalibration | None = None,
                zone_rects: np.ndarray | None = None,
                on_zones: Callable[[dict[str, Any]], None] | None = None) -> dict[str, Any]:
        """Build the network inputs for a batch of same-size images.

        Args:
            images: B images, each (H, W, 3) uint8 RGB, all of one size.
            frames: B zone frames of one grid size.
            calibration: optional rig calibration for (H, W) images.
            zone_rects: optional (B, Z, 4) (y0, x0, y1, x1) zone rectangles in pixels of
                the input images (e.g. a ZJU-L5 file's ``fr``); they replace the
                calibrated or nominal placement.
            on_zones: optional, called with the returned dict before its ``image`` is
                made (:meth:`predict` starts the blend's fill there).

        Returns:
            dict of numpy arrays, the network inputs (:meth:`run_network` takes them as
            they are): ``image`` (B, 3, h, w) float32 normalised, ``hypotheses`` (B, Z, K)
            float32 metres, ``zone_rects`` (B, Z, 4) float32 pixels of the network input,
            ``zone_valid`` (B, Z) bool, ``zone_no_target`` (B, Z) bool (the frames'
            no-target flags, inferred for a frame without them: :meth:`no_target_of`),
            ``zone_targets`` (B, Z, T, 2) float32 (every target of each zone,
            :func:`~deltar.sensor.targets.stacked_target_inputs`; T = 1 when no frame
            reports more than one); and ``image_rects`` (B, Z, 4) rectangles in
            input-image pixels, ``image_size`` (H, W) and ``network_size`` (h, w) in
            pixels (:meth:`network_size_for`).
        """
        checked = checks.check_batch_inputs(images, frames, self.max_range_m)
        size = checked[0].shape[:2]
        checks.check_calibration(calibration)
        net_size = self.network_size_for(size)
        if self.onnx_model is not None:
            self.onnx_model.check_grid(frames[0].grid, "frames[0]")
            self.onnx_model.warn_if_stretched(size, net_size)
        if zone_rects is not None:
            rects = np.asarray(zone_rects, dtype=np.float32)
            expected = (len(frames), frames[0].zone_count, 4)
            if rects.shape != expected or not np.all(np.isfinite(rects)):
                raise ValueError(f"zone_rects must be finite with shape {expected}, got "
                                 f"{rects.shape}")
        else:
            rects = np.stack([self.zone_rects_for(f, size, calibration) for f in frames])
        for i, frame in enumerate(frames):
            check_zones_in_image(rects[i], frame.flat()[2], size, f"frames[{i}]")
        inputs = {"hypotheses": np.stack([self.hypotheses_for(f) for f in frames]),
                  "zone_rects": scale_rects(rects, size, net_size),
                  "zone_valid": np.stack([f.flat()[2] for f in frames]),
                  "zone_no_target": np.stack([self.no_target_of(f) for f in frames]),
                  "zone_targets": stacked_target_inputs(frames),
                  "image_rects": rects, "image_size": size, "network_size": net_size}
        if on_zones is not None:
            on_zones(inputs)
        inputs["image"] = normalise_images(checked, net_size, self.image_mean, self.image_std)
        return inputs

    def run_network(self, inputs: dict[str, Any]) -> tuple[np.ndarray, np.ndarray]:
        """Run the network on :meth:`prepare`'s output: the one backend interface, numpy
        arrays in and out whichever backend runs (onnxruntime takes them as they are; the
        PyTorch model gets them as tensors on the estimator's device).

        Args:
            inputs: :meth:`prepare`'s dict (``image``, ``hypotheses``, ``zone_rects``,
                ``zone_valid`` and optionally ``zone_no_target`` and ``zone_targets`` are
                read; networks whose head does not read them ignore them).

        Returns:
            (depth, uncertainty), each (B, 1, h/2, w/2) float32 numpy arrays in metres.
        """
        no_target = inputs.get("zone_no_target")
        targets = inputs.get("zone_targets")
        if targets is not None and np.shape(targets)[2] < 2:
            targets = None  # the primary readings alone: what the zones already carry
        if self.onnx_model is not None:
            out = self.onnx_model.run(inputs["image"], inputs["hypotheses"],
                                      inputs["zone_rects"], inputs["zone_valid"], no_target,
                                      targets)
            return out["depth"], out["uncertainty"]
        from deltar.inference.torch_backend import run_torch_network

        return run_torch_network(self.model, self.device, self.dtype,
                                 (inputs["image"], inputs["hypotheses"], inputs["zone_rects"],
                                  inputs["zone_valid"], no_target, targets),
                                 self.flip_average)

    def predict(self, image: np.ndarray | Sequence[np.ndarray],
                zone_frame: ZoneFrame | Sequence[ZoneFrame],
                calibration: RigCalibration | None = None,
                zone_rects: np.ndarray | None = None,
                ) -> DepthPrediction | list[DepthPrediction]:
        """Predict depth for one image or a batch.

        Args:
            image: (H, W, 3) uint8 RGB image, or a list of them (one size).
            zone_frame: the matching ``ZoneFrame`` (or a list, one per image).
            calibration: optional rig calibration for images of its resolution; without
                it zones are placed with the nominal geometry. One with lens distortion
                undistorts the images first: the depth is for the undistorted image.
            zone_rects: optional (Z, 4) rectangles (or (B, Z, 4) for a batch) in pixels of
                the input image, replacing the calibrated or nominal placement.

        A frame with no valid zone gives an image-only estimate: its result says so as a
        value (``zones_used == 0``, ``image_only`` True) and its uncertainty is at least
        the depth itself (the metric scale is unknown); nothing is warned.

        Returns:
            A :class:`DepthPrediction` (depth and uncertainty in metres at the input
            resolution), or a list of them for list input.

        Raises:
            ValueError: bad image, zone frame (e.g. valid zones outside the sensor's
                range) or a calibration for another resolution.
        """
        started = self._begin_predict(image, zone_frame, calibration, zone_rects)
        return self._finish_predict(started, *self.run_network(started["inputs"]))

    def predict_stream(self, pairs: Iterable[tuple[np.ndarray, ZoneFrame]],
                       calibration: RigCalibration | None = None,
                       pipelined: bool | None = None) -> Iterator[DepthPrediction]:
        """:meth:`predict` for a stream of (image, zone frame) pairs: one result per
        pair, in order, each as ``predict(image, zone_frame, calibration)`` gives it.

        A pair is drawn and prepared on a worker thread while the previous frame's
        network runs on this one, and finished on another while the next one's does
        (:func:`~deltar.inference.stream.run_pipelined`). ``pipelined`` None (default)
        does so except where a PyTorch network's threads take every CPU core, where the
        frames run in turn; True / False always / never pipelines (docs/inference.md,
        "Streams"). A pair is kept until its result is handed out (a source must not
        refill it in place); a bad frame raises :meth:`predict`'s ``ValueError`` at its
        turn, after the results before it. Yields :class:`DepthPrediction` (metres).
        """
        from deltar.inference.stream import numbered_step, pipeline_chosen, run_pipelined

        # The schedule that runs the fill before the network tells where nothing is idle.
        in_turn = not fill_beside_network(self.model is not None) and self.device.type == "cpu"
        if not pipeline_chosen(pipelined, in_turn):
            step = numbered_step(lambda image, frame: self.predict(image, frame, calibration))
            return (step(item) for item in enumerate(pairs))
        begin = numbered_step(lambda image, frame: self._begin_predict(image, frame,
                                                                       calibration))
        return run_pipelined(enumerate(pairs), begin,
                             lambda started: self.run_network(started["inputs"]),
                             lambda started, outputs: self._finish_predict(started, *outputs))

    def _begin_predict(self, image: Any, zone_frame: Any,
                       calibration: RigCalibration | None = None,
                       zone_rects: np.ndarray | None = None) -> dict[str, Any]:
        """:meth:`predict` up to the network: the checked, screened and prepared batch
        (its inputs, the blend's fills started) as a dict :meth:`_finish_predict` reads."""
        single, images, frames = checks.batch_arguments(image, zone_frame)
        checks.check_calibration(calibration)  # before it undistorts the images
        if getattr(calibration, "has_distortion", False):  # other types refused in prepare
            # The zones are placed with the pinhole intrinsics: predict on the
            # undistorted image (same intrinsics), so depth is for that image.
            images = [calibration.undistort_image(np.asarray(im)) for im in images]
        # Outlying zones are set aside first: the network and the fill read the same zones.
        screened = [self.screen_zones(f) for f in frames]
        frames, rejected = [f for f, _ in screened], [r for _, r in screened]
        if zone_rects is not None:
            zone_rects = np.array(zone_rects, dtype=np.float32)  # results keep a copy
            zone_rects = zone_rects[None] if single and zone_rects.ndim == 2 else zone_rects
        # The blend's fill needs only the image and the zones: started once they are placed,
        # it runs while the images are resized and the network runs (all release the GIL).
        # One task, image part and all: a separate task for the image part started before
        # the zones were screened cost 0.4-0.5 ms a frame more (benchmarks/RESULTS.md).
        fills: list[Future] = []

        def start_fills(zones: dict[str, Any]) -> None:
            grid = tuple(side // 2 for side in zones["network_size"])
            fills.extend(self._start_fills(images, frames, zones["image_rects"],
                                           zones["zone_no_target"], grid))

        inputs = self.prepare(images, frames, calibration, zone_rects,
                              on_zones=None if self.blend is None else start_fills)
        return {"single": single, "frames": frames, "rejected": rejected, "inputs": inputs,
                "fills": fills, "calibration": calibration}

    def _finish_predict(self, started: dict[str, Any], depths: np.ndarray,
                        spreads: np.ndarray) -> DepthPrediction | list[DepthPrediction]:
        """:meth:`predict` from the network's (B, 1, h, w) depth and spread (metres) on:
        the output stage and the results."""
        inputs, fills, rejected = started["inputs"], started["fills"], started["rejected"]
        size, net_size = inputs["image_size"], inputs["network_size"]
        intrinsics = self.image_intrinsics(size, started["calibration"])
        results = []
        for i, frame in enumerate(started["frames"]):
            # Blend and sigma on the network's output grid, then one resize of what is
            # returned (deltar.inference.output_stage).
            grid_rects = scale_rects(inputs["image_rects"][i], size, depths.shape[2:])
            fill = fills[i].result() if fills else None
            far = (inputs["zone_no_target"][i], frame.range_limit_m(self.max_range_m))
            maps = [m for m in apply_output_stage(depths[i, 0], spreads[i, 0], fill, grid_rects,
                                                  self.blend, self.uncertainty,
                                                  frame.valid_count == 0, frame.flat(),
                                                  self.zone_consistency, far) if m is not None]
            maps = resize_to_image(np.stack(maps)[None], size, self.output_align_corners)[0]
            results.append(DepthPrediction(depth_m=maps[0], uncertainty_m=maps[1],
                                           zone_rects=inputs["image_rects"][i],
                                           zone_frame=copy.deepcopy(frame),
                                           intrinsics=intrinsics,
                                           zones_used=frame.valid_count,
                                           network_size=tuple(net_size),
                                           network_depth_m=maps[2] if len(maps) > 2 else None,
                                           uncertainty_calibrated=self.uncertainty
                                           is not None,
                                           zone_no_target=inputs["zone_no_target"][i],
                                           zone_rejected=rejected[i]))
        return results[0] if started["single"] else results

    def blend_fill_for(self, image: np.ndarray, frame: ZoneFrame, rects: np.ndarray,
                       out_size: tuple[int, int] | None = None) -> np.ndarray | None:
        """The fill the blend mixes with for one frame: (H, W) float32 metres, or None.

        Args:
            image: (H, W, 3) uint8 RGB image; ``frame`` its zone frame.
            rects: (Z, 4) zone rectangles in pixels of ``image`` (``DepthPrediction.
                zone_rects``).
            out_size: (h, w) pixels of the returned map (it covers the whole image); the
                image's size by default (``predict`` asks for its network's output grid).

        Returns:
            :func:`~deltar.inference.blend.blend_fill` of the zones (no-target zones read
            at the network's ``no_target_depth``), None without a valid zone on the image.
        """
        return self._start_fills([image], [frame], [rects], [self.no_target_of(frame)],
                                 out_size)[0].result()

    def screen_zones(self, frame: ZoneFrame) -> tuple[ZoneFrame, np.ndarray]:
        """:func:`~deltar.sensor.zone_outliers.reject_outlier_zones` with the estimator's
        rule; (frame, None) without one (or for a wrong type: :meth:`prepare` refuses it)."""
        if self.zone_outliers is None or not isinstance(frame, ZoneFrame):
            return frame, None
        return reject_outlier_zones(frame, self.zone_outliers, self.no_target_of(frame))

    def no_target_of(self, frame: ZoneFrame) -> np.ndarray:
        """(Z,) bool: the frame's no-target flags, inferred when it carries none
        (:func:`~deltar.sensor.no_target.frame_no_target`)."""
        return frame_no_target(frame, self.no_target_min_neighbour_m)

    def _start_fills(self, images: Sequence[np.ndarray], frames: Sequence[ZoneFrame],
                     rects: Sequence[np.ndarray], no_target: Sequence[np.ndarray],
                     out_size: tuple[int, int] | None = None) -> list[Future]:
        """:func:`~deltar.inference.fill_schedule.start_frame_fills` with the estimator's
        no-target depth and schedule (arguments as there)."""
        return start_frame_fills(images, frames, rects, no_target, self.no_target_depth_m,
                                 fill_beside_network(self.model is not None), out_size)
