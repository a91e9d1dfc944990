"""A bound on the request bodies held in memory at once: a JSON or OIP body is read only once the bytes it may take
are free, and they are freed when its registration has decoded it.

A request takes its slot before its body is read (``limiter.py``), so without this every queued request held its
whole body until a worker decoded it: 18 slots of 64 MiB bodies peaked above 1.1 GiB, past the manifest's limit.
Waiting here reads nothing: the body stays in the client's and the kernel's buffers. Holds are granted in arrival
order, so a large body is not passed over for ever by small ones.
"""

from __future__ import annotations

import asyncio
import threading
from collections import deque
from dataclasses import dataclass


@dataclass(eq=False)
class _Waiter:
    nbytes: int
    ready: asyncio.Future[None]
    granted: bool = False  # set under the budget's lock, before ``ready`` is resolved on its loop


class BodyBudget:
    """``capacity`` bytes of bodies at once; one body may take all of it."""

    def __init__(self, capacity: int):
        self.capacity = capacity
        self._lock = threading.Lock()  # released from worker threads, taken on the event loop
        self._held = 0
        self._waiting: deque[_Waiter] = deque()

    @property
    def held(self) -> int:
        """Bytes reserved by bodies being read or waiting to be decoded."""
        return self._held

    async def hold(self, nbytes: int) -> BodyHold:
        """A hold of ``nbytes`` (at most ``capacity``), once they are free and every earlier request has its own."""
        nbytes = min(nbytes, self.capacity)
        with self._lock:
            if not self._waiting and self._held + nbytes <= self.capacity:
                self._held += nbytes
                return BodyHold(self, nbytes)
            waiter = _Waiter(nbytes, asyncio.get_running_loop().create_future())
            self._waiting.append(waiter)
        try:
            await waiter.ready
        except asyncio.CancelledError:  # the request went away while it waited
            with self._lock:
                if waiter.granted:
                    self._give_back(nbytes)
                else:
                    self._waiting.remove(waiter)
                    self._grant()  # the next one may fit now
            raise
        return BodyHold(self, nbytes)

    def _give_back(self, nbytes: int) -> None:
        """Under the lock: ``nbytes`` freed, and the waiting holds that now fit granted in order."""
        self._held -= nbytes
        self._grant()

    def _grant(self) -> None:
        while self._waiting and self._held + self._waiting[0].nbytes <= self.capacity:
            waiter = self._waiting.popleft()
            self._held += waiter.nbytes
            waiter.granted = True
            waiter.ready.get_loop().call_soon_threadsafe(_resolve, waiter.ready)

    def _release(self, nbytes: int) -> None:
        with self._lock:
            self._give_back(nbytes)


def _resolve(granted: asyncio.Future[None]) -> None:
    if not granted.done():
        granted.set_result(None)


class BodyHold:
    """Bytes held for one body; ``release()`` frees them, once, from any thread (``with hold:`` does too)."""

    def __init__(self, budget: BodyBudget, nbytes: int):
        self._budget = budget
        self.nbytes = nbytes
        self._released = False
        self._lock = threading.Lock()

    def __enter__(self) -> BodyHold:
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def release(self) -> None:
        with self._lock:
            if self._released:
                return
            self._released = True
        self._budget._release(self.nbytes)
