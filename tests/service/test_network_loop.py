"""``service.network_loop``'s numeric helpers."""

from __future__ import annotations

import threading
import warnings

import numpy as np

from service.network_loop import DeferredOutput, lower_median_weights, sigmoid


def test_sigmoid_saturates_without_overflow_on_extreme_logits() -> None:
    logit = np.array([[-1e4, -800.0, 0.0, 800.0, 1e4]], dtype=np.float32)  # [B, K]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an overflow in exp would raise here
        value = sigmoid(logit)
    assert (value[0, :2] < 1e-300).all() and value[0, 2] == 0.5 and (value[0, 3:] == 1.0).all()
    assert value.dtype == np.float64


def test_sigmoid_equals_the_plain_formula_within_range() -> None:
    logit = np.linspace(-30, 30, 61, dtype=np.float32)[None]
    np.testing.assert_array_equal(sigmoid(logit), 1.0 / (1.0 + np.exp(-logit.astype(np.float64))))
    assert lower_median_weights(sigmoid(logit)).shape == logit.shape


def test_a_deferred_output_is_computed_once_when_first_read_even_from_two_threads() -> None:
    calls: list[int] = []
    computing, release = threading.Event(), threading.Event()

    def compute() -> str:
        calls.append(1)
        computing.set()
        release.wait(5.0)  # held until the second reader has started
        return "output"

    deferred = DeferredOutput(compute)  # type: ignore[arg-type]
    assert not deferred.computed and calls == []
    first, second = (threading.Thread(target=deferred.get) for _ in range(2))
    first.start()
    assert computing.wait(5.0) and not deferred.computed
    second.start()  # reads while the first computes
    second.join(0.1)
    release.set()
    for reader in (first, second):
        reader.join()
    assert deferred.get() == "output" and deferred.computed and calls == [1]
