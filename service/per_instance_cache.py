"""A cached property whose lock is its instance's own.

``functools.cached_property`` on Python 3.11 (the runtime's) takes one lock per attribute for every instance of the
class: while one registration computes, say, its ``Working.feature_pose`` on a large scan, every other registration's
first read of its own ``feature_pose`` waits. :class:`per_instance_cached_property` locks per instance and attribute,
so concurrent registrations never wait on each other, and a registration's two threads (the plain pass and the search
started ahead) still compute an attribute once.
"""

from __future__ import annotations

import threading
import weakref
from collections.abc import Callable
from typing import Any, Generic, TypeVar

T = TypeVar("T")


class per_instance_cached_property(Generic[T]):  # noqa: N801 -- a decorator, named as functools' is
    """``@per_instance_cached_property``: computed on the first read, kept in the instance's ``__dict__`` (which frozen
    dataclasses allow, as for ``functools.cached_property``), read from there afterwards without a lock. The locks
    live beside the instances (weakly keyed), not in them: an instance copies and pickles as it did."""

    def __init__(self, func: Callable[[Any], T]) -> None:
        self.func = func
        self.__doc__ = func.__doc__
        self.name = func.__name__
        self.locks: weakref.WeakKeyDictionary[Any, threading.Lock] = weakref.WeakKeyDictionary()
        self.guard = threading.Lock()  # held only to find or make an instance's lock

    def __set_name__(self, owner: type, name: str) -> None:
        self.name = name

    def __get__(self, instance: Any, owner: type | None = None) -> T:
        if instance is None:
            return self  # type: ignore[return-value]  -- the descriptor itself, read from the class
        cache = instance.__dict__
        if self.name in cache:
            return cache[self.name]
        with self.guard:
            lock = self.locks.setdefault(instance, threading.Lock())
        with lock:
            if self.name not in cache:
                cache[self.name] = self.func(instance)
            return cache[self.name]
