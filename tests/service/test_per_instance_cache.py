"""``service.per_instance_cache``: registrations never wait on each other's cached working attributes."""

from __future__ import annotations

import threading
from dataclasses import dataclass

from service.stages.normalise import Working

CACHED = type(vars(Working)["feature_pose"])  # the descriptor the working clouds' attributes use


@dataclass(frozen=True, eq=False)
class Slow:
    name: str
    started: threading.Event
    release: threading.Event

    @CACHED
    def value(self) -> str:
        """Waits for ``release`` when this is the instance named ``slow``."""
        self.started.set()
        if self.name == "slow":
            assert self.release.wait(10)
        return self.name


def test_reading_one_instance_does_not_wait_on_another_instance_computing():
    release = threading.Event()
    slow, quick = Slow("slow", threading.Event(), release), Slow("quick", threading.Event(), release)
    computing = threading.Thread(target=lambda: slow.value)
    computing.start()
    assert slow.started.wait(5)
    got = []
    reader = threading.Thread(target=lambda: got.append(quick.value))
    reader.start()
    reader.join(2)  # functools.cached_property on Python 3.11 holds one lock for both: the read would wait here
    finished_first = not reader.is_alive()
    release.set()
    computing.join(5)
    reader.join(5)
    assert finished_first and got == ["quick"] and slow.value == "slow"


def test_one_instance_computes_once_for_concurrent_readers():
    calls = []

    @dataclass(frozen=True, eq=False)
    class Counted:
        release: threading.Event

        @CACHED
        def value(self) -> int:
            """Counts its calls."""
            calls.append(1)
            assert self.release.wait(10)
            return 7

    one = Counted(threading.Event())
    got: list[int] = []
    readers = [threading.Thread(target=lambda: got.append(one.value)) for _ in range(4)]
    for reader in readers:
        reader.start()
    one.release.set()
    for reader in readers:
        reader.join(5)
    assert got == [7, 7, 7, 7] and len(calls) == 1
    assert one.value == 7 and len(calls) == 1  # from the instance's dict afterwards


def test_every_cached_working_attribute_locks_per_instance():
    cached = [name for name, value in vars(Working).items() if hasattr(value, "__get__") and hasattr(value, "func")]
    assert len(cached) >= 20 and all(isinstance(vars(Working)[name], CACHED) for name in cached)
    assert CACHED.__module__ == "service.per_instance_cache"


def test_an_instance_copies_and_pickles_after_a_cached_read():
    """The locks live beside the instances: one kept in the instance's dict made deepcopy and pickle fail."""
    import copy
    import pickle

    one = Plain(3)
    assert one.doubled == 6
    assert copy.deepcopy(one).doubled == 6 and pickle.loads(pickle.dumps(one)).doubled == 6


@dataclass(frozen=True, eq=False)
class Plain:
    value: int

    @CACHED
    def doubled(self) -> int:
        """Twice the value."""
        return 2 * self.value
