"""The evaluation loop and the method registry."""

from __future__ import annotations

import numpy as np
import pytest

from deltar.evaluation import runner
from deltar.evaluation.baselines import BASELINES
from deltar.evaluation.metrics import depth_metrics
from deltar.evaluation.runner import (
    BaselinePredictor,
    create_predictor,
    evaluate_methods,
    register_method,
    register_method_family,
    resolve_method_names,
)

from .samples import make_sample


@pytest.fixture
def clean_registry(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(runner, "_METHODS", dict(runner._METHODS))
    monkeypatch.setattr(runner, "_FAMILIES", dict(runner._FAMILIES))


def test_resolve_method_names() -> None:
    assert resolve_method_names("all") == list(BASELINES)
    assert resolve_method_names("bilinear, nearest,bilinear") == ["bilinear", "nearest"]
    with pytest.raises(ValueError, match="valid methods: all, median, nearest"):
        resolve_method_names("nearest,magic")
    with pytest.raises(ValueError, match="no method"):
        resolve_method_names(" , ")


def test_registry_accepts_methods_and_families(clean_registry: None) -> None:
    register_method("const3", lambda: lambda sample: np.full(sample.depth_m.shape, 3.0))
    register_method_family("testfam", lambda name: lambda sample: np.full(
        sample.depth_m.shape, float(len(name))))
    assert "testfam:NAME" in runner.available_methods()
    assert resolve_method_names("const3,testfam:abcd") == ["const3", "testfam:abcd"]
    sample = make_sample("x", 0)
    assert create_predictor("testfam:abcd")(sample)[0, 0] == 4.0
    assert create_predictor("const3")(sample)[0, 0] == 3.0
    with pytest.raises(ValueError, match="already registered"):
        register_method("const3", lambda: None)
    with pytest.raises(ValueError, match="unknown method 'testfam:'"):
        resolve_method_names("testfam:")
    with pytest.raises(ValueError, match="invalid method name"):
        register_method("a:b", lambda: None)


def test_nearest_is_exact_on_blocky_frames(tiny_samples) -> None:
    result = evaluate_methods(tiny_samples, {"nearest": BaselinePredictor("nearest")})
    metrics = result.metrics["nearest"]
    assert result.frames == 3 and result.skipped == 0
    assert metrics["d1"] == 1.0
    assert metrics["rel"] == pytest.approx(0.0, abs=1e-6)
    assert metrics["rmse"] == pytest.approx(0.0, abs=1e-6)


def test_averages_per_frame_and_limit(tiny_samples) -> None:
    def constant(sample):
        return np.full(sample.depth_m.shape, 1.5, dtype=np.float32)

    result = evaluate_methods(tiny_samples, {"constant": constant}, limit=2)
    expected = np.mean([depth_metrics(np.full((32, 48), 1.5), s.depth_m)["rel"]
                        for s in tiny_samples[:2]])
    assert result.frames == 2
    assert result.metrics["constant"]["rel"] == pytest.approx(expected)


def test_on_frame_receives_every_prediction(tiny_samples) -> None:
    seen = []
    evaluate_methods(tiny_samples, {"nearest": BaselinePredictor("nearest"),
                                    "bilinear": BaselinePredictor("bilinear")},
                     on_frame=lambda i, s, preds: seen.append((i, s.name, sorted(preds))))
    assert seen == [(0, "scene_a/0001", ["bilinear", "nearest"]),
                    (1, "scene_a/0002", ["bilinear", "nearest"]),
                    (2, "scene_b/0001", ["bilinear", "nearest"])]


def test_frames_without_ground_truth_are_skipped(tiny_samples) -> None:
    samples = [*tiny_samples[:1], make_sample("empty", 5, empty_gt=True)]
    with pytest.warns(RuntimeWarning, match="skipping frame 'empty'"):
        result = evaluate_methods(samples, {"nearest": BaselinePredictor("nearest")})
    assert result.frames == 1 and result.skipped == 1
    assert np.isfinite(list(result.metrics["nearest"].values())).all()
    with pytest.warns(RuntimeWarning), pytest.raises(ValueError, match="none of the 1 frames"):
        evaluate_methods(samples[1:], {"nearest": BaselinePredictor("nearest")})


def test_bad_predictions_name_the_method(tiny_samples) -> None:
    with pytest.raises(ValueError, match="method 'half' returned shape"):
        evaluate_methods(tiny_samples, {"half": lambda s: np.ones((16, 24))})
    with pytest.raises(ValueError, match="method 'nan' returned NaN"):
        evaluate_methods(tiny_samples, {"nan": lambda s: np.full((32, 48), np.nan)})
    with pytest.raises(ValueError, match="predictors is empty"):
        evaluate_methods(tiny_samples, {})


def test_a_method_refusing_a_frame_is_named_with_the_frame(tiny_samples) -> None:
    def refuses(sample):
        raise ValueError("frames[0] has 4x4 zones")

    name = tiny_samples[0].name
    with pytest.raises(ValueError, match=f"method 'picky', frame '{name}': frames.0. has 4x4"):
        evaluate_methods(tiny_samples, {"picky": refuses})


class _ListedFrames(list):
    """Samples of a set that names each frame's files (as ZJUL5Dataset does)."""

    def frame_files(self, index):
        return [f"set/{self[index].name}.h5"]


def test_a_frame_whose_zones_all_lie_outside_the_image_is_refused_for_every_method(
        tiny_samples) -> None:
    import dataclasses

    away = dataclasses.replace(tiny_samples[1], zone_rects=tiny_samples[1].zone_rects + 1e5)
    frames = _ListedFrames([tiny_samples[0], away])
    scored = []
    with pytest.raises(ValueError, match=r"^frame 'scene_a/0002' \(set/scene_a/0002\.h5\): "
                       r"all 16 valid zones fall outside the 32x48 image"):
        evaluate_methods(frames, {"nearest": BaselinePredictor("nearest"),
                                  "spy": lambda s: scored.append(s.name) or s.depth_m})
    assert scored == ["scene_a/0001"]  # refused before any method ran on it


def test_keep_going_leaves_a_refused_frame_out_for_every_method(tiny_samples) -> None:
    import dataclasses

    away = dataclasses.replace(tiny_samples[1], zone_rects=tiny_samples[1].zone_rects + 1e5)
    frames = _ListedFrames([tiny_samples[0], away, tiny_samples[2]])
    seen = []
    with pytest.warns(RuntimeWarning, match=r"leaving out frame 'scene_a/0002': frame "
                      r"'scene_a/0002' \(set/scene_a/0002\.h5\): all 16 valid zones"):
        result = evaluate_methods(frames, {"nearest": BaselinePredictor("nearest")},
                                  keep_going=True,
                                  on_frame=lambda i, s, p: seen.append((i, sorted(p))))
    assert result.frames == 2 and [name for name, _ in result.refused] == ["scene_a/0002"]
    assert seen == [(0, ["nearest"]), (1, []), (2, ["nearest"])]
    kept = evaluate_methods([tiny_samples[0], tiny_samples[2]],
                            {"nearest": BaselinePredictor("nearest")})
    assert result.metrics == kept.metrics  # the same two frames, the same averages

    def picky(sample):  # a method refusing one frame leaves it out for the others too
        if sample.name == "scene_b/0001":
            raise ValueError("4x4 zones")
        return sample.depth_m

    with pytest.warns(RuntimeWarning, match="method 'picky', frame 'scene_b/0001': 4x4"):
        result = evaluate_methods(tiny_samples, {"nearest": BaselinePredictor("nearest"),
                                                 "picky": picky}, keep_going=True)
    assert result.frames == 2 and result.refused[0][0] == "scene_b/0001"
    with pytest.warns(RuntimeWarning), pytest.raises(ValueError, match=r"all 1 frames were "
                                                     r"left out \(first: method 'picky'"):
        evaluate_methods(tiny_samples[2:], {"picky": picky}, keep_going=True)


def test_baseline_predictor_ignores_valid_zones_without_distance() -> None:
    sample = make_sample("zero", 0)
    sample.zone_mean_sigma[3, 0] = 0.0  # flagged valid, but no distance reported
    depth = BaselinePredictor("nearest")(sample)
    assert depth.min() > 0
    # Zone 3 covers rows 0..7, columns 32..39; pixel (0, 32) is 1 px from zone 2's
    # pixel (0, 31) and 8 px from zone 7's pixel (8, 32).
    assert depth[0, 32] == sample.zone_mean_sigma[2, 0]


def test_far_baselines_read_zones_with_no_target_at_the_far_depth() -> None:
    from deltar.sensor.zone_frame import NO_TARGET_DEPTH_M

    sample = make_sample("far", 0)
    sample.zone_valid[3] = False
    sample.zone_mean_sigma[3] = 0.0
    classic = create_predictor("nearest")(sample)
    assert create_predictor("nearest+far")(sample)[0, 32] == classic[0, 32]  # no flags
    sample.zone_no_target = np.zeros_like(sample.zone_valid)
    sample.zone_no_target[3] = True
    far = create_predictor("nearest+far")(sample)
    # Zone 3 covers rows 0..7, columns 32..39.
    assert np.all(far[:8, 32:40] == np.float32(NO_TARGET_DEPTH_M))
    assert classic[0, 32] == sample.zone_mean_sigma[2, 0]
    np.testing.assert_array_equal(create_predictor("nearest")(sample), classic)
    assert "nearest+far" not in resolve_method_names("all")


def test_resize_like_release_aligns_corners() -> None:
    from deltar.evaluation.runner import resize_like_release

    depth = np.array([[1.0, 3.0], [5.0, 7.0]])
    resized = resize_like_release(depth, 3, 3)
    # align_corners=True keeps the corners and puts the new samples half way between.
    expected = np.array([[1.0, 2.0, 3.0], [3.0, 4.0, 5.0], [5.0, 6.0, 7.0]])
    np.testing.assert_allclose(resized, expected, atol=1e-6)
    assert resized.dtype == np.float32
    with pytest.raises(ValueError, match="depth_m"):
        resize_like_release(np.ones(3), 2, 2)


def test_methods_that_give_a_sigma_are_scored_for_coverage() -> None:
    from types import SimpleNamespace

    samples = [make_sample("a/1", 0), make_sample("a/2", 1)]

    def with_sigma(sample):
        # Every pixel off by 0.1 m: inside two sigma of 0.06 m, outside one.
        return SimpleNamespace(depth_m=sample.depth_m + 0.1,
                               uncertainty_m=np.full_like(sample.depth_m, 0.06))

    result = evaluate_methods(samples, {"sigma": with_sigma, "nearest": create_predictor(
        "nearest")})
    assert result.metrics["sigma"]["within_1sigma"] == 0.0
    assert result.metrics["sigma"]["within_2sigma"] == 1.0
    assert result.metrics["sigma"]["rmse"] == pytest.approx(0.1, abs=1e-6)
    assert "within_1sigma" not in result.metrics["nearest"]


def test_resize_like_release_clips_to_the_depth_range_before_resizing() -> None:
    from deltar.evaluation.runner import resize_like_release

    # The release clips to [min_depth, max_depth] first, then interpolates: the middle
    # sample is half way between the clipped ends, not between 0 and 20 (then clipped).
    resized = resize_like_release(np.array([[0.0, 20.0]]), 1, 3, min_depth=1e-3,
                                  max_depth=10.0)
    np.testing.assert_allclose(resized, [[1e-3, (1e-3 + 10.0) / 2, 10.0]], rtol=1e-6)
    # Without a range nothing is clipped, as before: a method evaluated with --max-depth 20
    # that calls resize_like_release(depth, H, W) keeps its depth beyond 10 m.
    np.testing.assert_allclose(resize_like_release(np.array([[0.0, 20.0]]), 1, 3),
                               [[0.0, 10.0, 20.0]], rtol=1e-6)
    narrow = resize_like_release(np.array([[0.0, 20.0]]), 1, 3, min_depth=1.0, max_depth=3.0)
    np.testing.assert_allclose(narrow, [[1.0, 2.0, 3.0]], rtol=1e-6)
    with pytest.raises(ValueError, match="min_depth"):
        resize_like_release(np.ones((2, 2)), 2, 2, min_depth=3.0, max_depth=1.0)
