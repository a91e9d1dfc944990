"""Work started ahead on a spare core (service.speculation), and auto's search run beside the plain pass with it."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from shapes import asymmetric_blob

from service import kdtree
from service.manifest import bundled_models_dir
from service.registrar import Registrar
from service.speculation import CancelledError, Helpers, check

GENERAL = bundled_models_dir() / "general"


def wait_until_idle(helpers: Helpers, seconds: float = 5.0) -> None:
    deadline = time.monotonic() + seconds
    while helpers.busy and time.monotonic() < deadline:
        time.sleep(0.005)
    assert helpers.busy == 0


def test_work_runs_in_a_helper_thread_and_its_result_comes_back() -> None:
    helpers = Helpers(2)
    with helpers.registering():
        ahead = helpers.start(lambda cancelled: threading.current_thread().name)
        assert ahead is not None and ahead.result().startswith("mfgnet-helper")
    wait_until_idle(helpers)


def test_no_helper_starts_while_every_core_is_busy() -> None:
    helpers = Helpers(2)
    with helpers.registering(), helpers.registering():  # two registrations fill both cores
        assert helpers.start(lambda cancelled: 1) is None
    assert helpers.busy == 0


def test_one_core_never_starts_a_helper_beside_its_registration() -> None:
    helpers = Helpers(1)
    with helpers.registering():
        assert helpers.start(lambda cancelled: 1) is None


def test_kd_tree_queries_of_busy_threads_share_the_cores() -> None:
    """A registration alone gets both cores for its large KD-tree queries; with its helper at work, or beside a
    second registration, one each; outside every block none is shared."""
    helpers = Helpers(2)
    with helpers.registering():
        alone = kdtree._sharing.cores()
        ahead = helpers.start(lambda cancelled: (kdtree._sharing.cores(), helpers.share()))
        assert ahead is not None
        in_helper, while_helping = ahead.result()
    with helpers.registering(), helpers.registering():  # two registrations at once
        two = helpers.share()
    assert (alone, in_helper, while_helping, two) == (2, 1, 1, 1)
    assert getattr(kdtree._sharing, "cores", None) is None
    wait_until_idle(helpers)


def test_cancelled_work_stops_at_its_next_check_and_frees_its_core() -> None:
    helpers = Helpers(2)
    running = threading.Event()

    def endless(cancelled: threading.Event) -> None:
        running.set()
        while True:
            check(cancelled)
            time.sleep(0.001)

    ahead = helpers.start(endless)
    assert ahead is not None and running.wait(5)
    ahead.cancel()
    with pytest.raises(CancelledError):
        ahead.result()
    wait_until_idle(helpers)


def test_work_cancelled_before_a_helper_takes_it_never_runs() -> None:
    helpers = Helpers(3)  # two helper threads: the third piece of work waits in the queue
    release, ran = threading.Event(), []
    blockers = [helpers.start(lambda cancelled: release.wait(5)) for _ in range(2)]
    queued = helpers.start(lambda cancelled: ran.append(True))
    assert None not in blockers and queued is not None
    queued.cancel()
    release.set()
    assert all(b.result() for b in blockers)
    wait_until_idle(helpers)
    assert ran == []


def test_an_error_of_the_work_reaches_the_caller_and_frees_its_core() -> None:
    helpers = Helpers(2)

    def failing(cancelled: threading.Event) -> None:
        raise ValueError("bad input")

    ahead = helpers.start(failing)
    with pytest.raises(ValueError, match="bad input"):
        ahead.result()
    wait_until_idle(helpers)


class CountingHelpers(Helpers):
    """Real helpers that count the work they started."""

    def __init__(self, cores: int):
        super().__init__(cores)
        self.started = 0

    def start(self, work):
        ahead = super().start(work)
        self.started += ahead is not None
        return ahead


@pytest.mark.skipif(not (GENERAL / "manifest.json").exists(), reason="bundled model 'general' absent")
def test_auto_search_run_ahead_gives_the_result_of_the_search_run_after() -> None:
    src = asymmetric_blob(1500, 3)
    turn = Rotation.from_euler("zyx", [150.0, -40.0, 70.0], degrees=True).as_matrix()
    tgt = src @ turn.T + np.array([0.2, -0.1, 0.3])
    ahead, after = CountingHelpers(2), CountingHelpers(1)  # one core: the search runs after the plain pass
    with_ahead = Registrar(GENERAL, threads=2, helpers=ahead, warmup=False)
    with_after = Registrar(GENERAL, threads=2, helpers=after, warmup=False)
    a = with_ahead.register(src, tgt, refine="icp-plane", rotation_search="auto")
    b = with_after.register(src, tgt, refine="icp-plane", rotation_search="auto")
    assert ahead.started == 1 and after.started == 0
    assert "search" in a.timing_ms and "search" in b.timing_ms
    np.testing.assert_array_equal(a.transform, b.transform)
    assert (a.reliable, a.warnings, a.inlier_ratio) == (b.reliable, b.warnings, b.inlier_ratio)
    wait_until_idle(ahead)


@pytest.mark.skipif(not (GENERAL / "manifest.json").exists(), reason="bundled model 'general' absent")
def test_a_pair_the_plain_network_fits_starts_nothing_ahead() -> None:
    src = asymmetric_blob(1500, 4)
    turn = Rotation.from_euler("zyx", [10.0, -5.0, 5.0], degrees=True).as_matrix()
    helpers = CountingHelpers(2)
    result = Registrar(GENERAL, threads=2, helpers=helpers, warmup=False).register(
        src, src @ turn.T + 0.05, refine="icp-plane", rotation_search="auto")
    assert helpers.started == 0 and "search" not in result.timing_ms
