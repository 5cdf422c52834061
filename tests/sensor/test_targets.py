"""Every target of a zone as the network reads it (deltar.sensor.targets)."""

from __future__ import annotations

import numpy as np

from deltar.sensor.targets import stacked_target_inputs, target_inputs
from deltar.sensor.zone_frame import ZoneFrame


def _frame(order: str = "strongest", signal: bool = True) -> ZoneFrame:
    mean = np.full((4, 4), 1.0, np.float32)
    valid = np.ones((4, 4), bool)
    valid[3, 3] = False
    mean[3, 3] = 0.0
    sigma = np.full((4, 4), 0.02, np.float32) * valid
    t_mean = np.zeros((4, 4, 3), np.float32)
    t_sigma = np.zeros((4, 4, 3), np.float32)
    t_valid = np.zeros((4, 4, 3), bool)
    t_mean[..., 0], t_sigma[..., 0], t_valid[..., 0] = mean, sigma, valid
    # Zone (0, 0) also sees 2 m (and 3.5 m); zone (0, 1) sees 2.5 m.
    t_mean[0, 0, 1:], t_sigma[0, 0, 1:], t_valid[0, 0, 1:] = (2.0, 3.5), 0.05, True
    t_mean[0, 1, 1], t_sigma[0, 1, 1], t_valid[0, 1, 1] = 2.5, 0.05, True
    extra = {}
    if signal:
        # Signal falls with the squared distance: these are equal areas at 1 and 2 m
        # and a quarter of that at 3.5 m.
        t_signal = np.zeros((4, 4, 3), np.float32)
        t_signal[..., 0] = valid * 1.0
        t_signal[0, 0, 1:] = (1 / 4, 0.25 / 3.5**2)
        t_signal[0, 1, 1] = 1 / 2.5**2
        extra["target_signal"] = t_signal
    return ZoneFrame(mean, sigma, valid, target_mean_m=t_mean, target_sigma_m=t_sigma,
                     target_valid=t_valid, target_order=order, **extra)


def test_target_inputs_put_the_primary_first_with_shares_from_signal_and_distance():
    inputs = target_inputs(_frame())
    assert inputs.shape == (16, 3, 2)
    np.testing.assert_allclose(inputs[0], [[1.0, 1 / 2.25], [2.0, 1 / 2.25],
                                           [3.5, 0.25 / 2.25]], rtol=1e-5)
    np.testing.assert_allclose(inputs[1], [[1.0, 0.5], [2.5, 0.5], [0.0, 0.0]], rtol=1e-5)
    np.testing.assert_allclose(inputs[2], [[1.0, 1.0], [0.0, 0.0], [0.0, 0.0]])
    np.testing.assert_array_equal(inputs[15], 0.0)  # invalid zone


def test_without_signals_every_target_weighs_alike():
    inputs = target_inputs(_frame(signal=False))
    np.testing.assert_allclose(inputs[0, :, 1], [1 / 3, 1 / 3, 1 / 3], rtol=1e-6)
    np.testing.assert_allclose(inputs[1, :, 1], [0.5, 0.5, 0.0], rtol=1e-6)


def test_a_single_target_frame_gives_one_slot_and_batches_pad_to_the_used_slots():
    mean = np.full((4, 4), 1.5, np.float32)
    single = ZoneFrame(mean, mean * 0.01, np.ones((4, 4), bool))
    inputs = target_inputs(single)
    assert inputs.shape == (16, 1, 2)
    np.testing.assert_allclose(inputs[..., 0, 0], 1.5)
    np.testing.assert_allclose(inputs[..., 0, 1], 1.0)
    batch = stacked_target_inputs([single, _frame()])
    assert batch.shape == (2, 16, 2, 2)  # at most NETWORK_TARGET_SLOTS: the largest kept
    np.testing.assert_array_equal(batch[0, :, 1:], 0.0)
    np.testing.assert_allclose(batch[1, 0], [[1.0, 1 / 2.25], [2.0, 1 / 2.25]], rtol=1e-5)
    fixed = stacked_target_inputs([single, _frame()], slots=3)
    assert fixed.shape == (2, 16, 3, 2)
    np.testing.assert_allclose(fixed[1, 0, 2], [3.5, 0.25 / 2.25], rtol=1e-5)
    # A multi-target frame whose zones report one target each: one slot.
    frame = _frame()
    frame.target_valid[..., 1:] = False
    frame.target_mean_m[..., 1:] = 0.0
    assert stacked_target_inputs([frame]).shape == (1, 16, 1, 2)


def test_in_closest_first_order_the_primary_is_found_wherever_it_stands():
    # Zone (0, 0) read closest first: targets at 1.0, 2.0 and 3.5 m, the primary (the
    # strongest return) the second of them.
    frame = _frame()
    mean = frame.mean_m.copy()
    mean[0, 0] = 2.0
    t_mean = frame.target_mean_m.copy()
    t_mean[0, 0] = (1.0, 2.0, 3.5)
    t_signal = frame.target_signal.copy()
    t_signal[0, 0] = (1.0, 1 / 4, 0.25 / 3.5**2)
    closest = ZoneFrame(mean, frame.sigma_m, frame.valid, target_mean_m=t_mean,
                        target_sigma_m=frame.target_sigma_m, target_valid=frame.target_valid,
                        target_signal=t_signal, target_order="closest")
    inputs = target_inputs(closest)
    np.testing.assert_allclose(inputs[0], [[2.0, 1 / 2.25], [1.0, 1 / 2.25],
                                           [3.5, 0.25 / 2.25]], rtol=1e-5)
