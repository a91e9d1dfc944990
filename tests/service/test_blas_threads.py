"""service.blas_threads: numpy's BLAS at one thread for the whole process once a registrar or the app is built."""

from __future__ import annotations

import threading

import pytest
from threadpoolctl import threadpool_limits

from service.api.app import create_app
from service.blas_threads import blas_thread_counts, use_one_blas_thread
from service.core.config import Settings
from service.manifest import bundled_models_dir
from service.registrar import Registrar

BUNDLED = bundled_models_dir() / "clean"


def counts_in_another_thread() -> list[int]:
    seen: list[int] = []
    worker = threading.Thread(target=lambda: seen.extend(blas_thread_counts()))
    worker.start()
    worker.join(5)
    return seen


@pytest.fixture
def three_blas_threads():
    """Every BLAS runtime at three threads, restored to the process's counts afterwards."""
    if not blas_thread_counts():
        pytest.skip("no BLAS runtime loaded in this process")
    with threadpool_limits(3, user_api="blas"):
        if set(blas_thread_counts()) != {3}:
            pytest.skip("this BLAS build does not take a thread count")
        yield


def test_the_main_thread_sets_one_thread_for_every_thread(three_blas_threads) -> None:
    assert use_one_blas_thread() is True
    assert set(blas_thread_counts()) == {1}
    assert set(counts_in_another_thread()) == {1}


def test_another_thread_cannot_and_says_so(three_blas_threads) -> None:
    answers: list[bool] = []
    worker = threading.Thread(target=lambda: answers.append(use_one_blas_thread()))
    worker.start()
    worker.join(5)
    assert answers == [False]
    assert set(blas_thread_counts()) == {3}


@pytest.mark.skipif(not (BUNDLED / "manifest.json").exists(), reason="bundled model 'clean' absent")
def test_a_registrar_built_on_the_main_thread_sets_it(three_blas_threads) -> None:
    Registrar(BUNDLED, threads=1, warmup=False)
    assert set(counts_in_another_thread()) == {1}


def test_the_app_sets_it_before_its_models_load_in_a_background_thread(three_blas_threads) -> None:
    create_app(Settings(models=["clean"]))
    assert set(counts_in_another_thread()) == {1}
