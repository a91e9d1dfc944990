"""A cancelled registration stops at its next network call, in its own thread and in the helper running its search
ahead; an uncancelled one, and every call outside a request, runs exactly as before (``service.cancellation``)."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from shapes import bumpy_ellipsoid

from service.cancellation import Cancellation, RegistrationCancelledError, cancellable, run_options
from service.manifest import bundled_models_dir
from service.registrar import Registrar
from service.speculation import Helpers

HEAVY = {"refine": "none", "rotation_search": True, "keypoints": 512, "iterations": 8}  # tens of seconds


@pytest.fixture(scope="module")
def registrar() -> Registrar:
    return Registrar(bundled_models_dir() / "general", threads=1)


def test_outside_a_request_no_run_options_are_passed() -> None:
    assert run_options() is None


def test_a_cancelled_registration_stops_within_a_moment_and_the_registrar_carries_on(registrar) -> None:
    rng = np.random.default_rng(0)
    source, target = rng.normal(size=(20_000, 3)), rng.normal(size=(20_000, 3))
    cancellation, outcome = Cancellation(), {}

    def register() -> None:
        try:
            with cancellable(cancellation):
                registrar.register(source, target, **HEAVY)
            outcome["ended"] = "finished"
        except RegistrationCancelledError:
            outcome["ended"] = "cancelled"

    worker = threading.Thread(target=register)
    worker.start()
    time.sleep(0.5)
    cancelled_at = time.perf_counter()
    cancellation.cancel()
    worker.join(timeout=10)
    assert not worker.is_alive() and outcome["ended"] == "cancelled"
    assert time.perf_counter() - cancelled_at < 2.0  # the search alone would run for tens of seconds
    with pytest.raises(RegistrationCancelledError), cancellable(cancellation):
        registrar.register(source[:500], target[:500])  # once cancelled, a request's next call stops at once
    cloud = bumpy_ellipsoid(600)
    alone = registrar.register(cloud, cloud + 0.1)
    with cancellable(Cancellation()):  # a request that is not cancelled: the same result as a library call
        inside = registrar.register(cloud, cloud + 0.1)
    np.testing.assert_array_equal(alone.rotation, inside.rotation)
    np.testing.assert_array_equal(alone.translation, inside.translation)


def test_work_handed_to_a_helper_carries_the_requests_cancellation() -> None:
    helpers = Helpers(cores=2)
    cancellation = Cancellation()
    with cancellable(cancellation):
        started = helpers.start(lambda cancelled: run_options())
    assert started is not None and started.result() is cancellation.run_options
    cancellation.cancel()
    with cancellable(cancellation):
        cancelled = helpers.start(lambda cancelled: run_options())
    with pytest.raises(RegistrationCancelledError):
        cancelled.result()
    assert helpers.busy == 0
