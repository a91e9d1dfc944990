"""Bounded concurrency for the CPU-heavy work: ``max_concurrency`` worker threads, at most
``max_queue`` requests waiting for one (beyond that: 503 at once), and a deadline (504).

A request takes a :class:`Slot` before its body is read, so an overloaded server refuses quickly.
A job that outlives its deadline is cancelled (:mod:`service.cancellation`): it stops at its next network call,
and its slot stays taken until then, so abandoned work counts against the limits only that long.
"""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Awaitable, Callable
from concurrent.futures import Future, ThreadPoolExecutor
from typing import Any, TypeVar

from starlette.requests import ClientDisconnect

from service.api.errors import APIError
from service.cancellation import Cancellation, cancellable

T = TypeVar("T")

RETRY_AFTER_OVERLOADED_S = 1
DISCONNECT_POLL_S = 0.25  # how often a waiting request asks whether its client is still there


class OverloadedError(APIError):
    def __init__(self, capacity: int):
        super().__init__(
            503,
            f"server is busy ({capacity} registration{'' if capacity == 1 else 's'} running or waiting); retry later",
            headers={"Retry-After": str(RETRY_AFTER_OVERLOADED_S)},
        )


class DeadlineExceededError(APIError):
    def __init__(self, timeout_s: float):
        super().__init__(504, f"registration did not finish within {timeout_s:g} s (MFGNET_TIMEOUT_S)")


class AlignedBusyError(APIError):
    def __init__(self, capacity: int):
        super().__init__(
            503,
            f"server is busy ({capacity} aligned file{'' if capacity == 1 else 's'} being written or sent); "
            "retry later",
            headers={"Retry-After": str(RETRY_AFTER_OVERLOADED_S)},
        )


class InferenceLimiter:
    """One thread pool shared by all requests (the ONNX sessions are thread-safe and shared too)."""

    def __init__(self, max_concurrency: int, max_queue: int, timeout_s: float):
        self.max_concurrency = max_concurrency
        self.capacity = max_concurrency + max_queue
        self.timeout_s = timeout_s
        self._executor = ThreadPoolExecutor(max_workers=max_concurrency, thread_name_prefix="mfgnet-infer")
        self._lock = threading.Lock()
        self._taken = 0
        self._running = 0
        self._answers = 0  # aligned answers being made or sent (admit_answer)

    @property
    def taken(self) -> int:
        """Slots held: requests being read, waiting or running, plus abandoned jobs still running."""
        return self._taken

    @property
    def running(self) -> int:
        return self._running

    def admit(self) -> Slot:
        """A slot, or :class:`OverloadedError` when ``max_concurrency + max_queue`` are taken."""
        with self._lock:
            if self._taken >= self.capacity:
                raise OverloadedError(self.capacity)
            self._taken += 1
        return Slot(self)

    def admit_answer(self) -> Callable[[], None]:
        """A place for one aligned answer (``/v1/register/aligned``) from its upload until its moved file has been
        sent, or :class:`AlignedBusyError` when ``max_concurrency`` are taken: the moved files on disk (up to twice
        their upload) stay as many as the workers. Returns its release, which may be called more than once."""
        with self._lock:
            if self._answers >= self.max_concurrency:
                raise AlignedBusyError(self.max_concurrency)
            self._answers += 1
        released = threading.Event()

        def release() -> None:
            with self._lock:
                if not released.is_set():
                    released.set()
                    self._answers -= 1

        return release

    def _release(self) -> None:
        with self._lock:
            self._taken -= 1

    def _submit(self, fn: Callable[[], T]) -> Future:
        # The executor keeps a cancelled job's work item in its queue until a worker takes it off; the job's callable
        # (and through it the request's spooled upload files or body) must not live that long: it is dropped here as
        # soon as the job is cancelled before it started (the client gone, or its deadline passed in the queue).
        held: list[Callable[[], T]] = [fn]

        def job() -> T:
            with self._lock:
                self._running += 1
            try:
                return held[0]()
            finally:
                held.clear()
                with self._lock:
                    self._running -= 1

        future = self._executor.submit(job)
        future.add_done_callback(lambda f: held.clear() if f.cancelled() else None)
        return future

    def shutdown(self) -> None:
        self._executor.shutdown(wait=False, cancel_futures=True)


class Slot:
    """A place in the limiter; ``release()`` it exactly once (``with slot:`` does)."""

    def __init__(self, limiter: InferenceLimiter):
        self._limiter = limiter
        self._future: Future | None = None
        self._released = False

    def __enter__(self) -> Slot:
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    async def run(self, fn: Callable[..., T], disconnected: Callable[[], Awaitable[bool]] | None = None,
                  decode: Callable[[], Any] | None = None) -> tuple[T, float]:
        """``(fn(), ms waited for a worker)``, run in the pool within ``timeout_s``; ``disconnected``: asked every
        ``DISCONNECT_POLL_S`` while the job waits or runs, ``True`` once the client has gone (the job is cancelled and
        Starlette's ``ClientDisconnect`` raised, which the access middleware records as 499 as it does for a body
        cut short).

        ``decode`` (the request's body into clouds): the job is ``fn(decode())`` and the deadline stops while
        ``decode`` runs, so a body it refuses from its size (413 over max_points) is refused whatever ``timeout_s``;
        the wait for a worker and ``fn`` count. Its time is bounded by the body's size limits."""
        if self._future is not None:
            raise RuntimeError("a slot runs one job")
        submitted = time.perf_counter()
        started: list[float] = []
        decoding: list[float] = []  # decode's start, then its end
        cancellation = Cancellation()

        def timed() -> T:
            started.append(time.perf_counter())
            with cancellable(cancellation):
                if decode is None:
                    return fn()
                decoding.append(time.perf_counter())
                try:
                    decoded = decode()
                finally:
                    decoding.append(time.perf_counter())
                return fn(decoded)

        self._future = self._limiter._submit(timed)
        job = asyncio.wrap_future(self._future)
        timeout_s = self._limiter.timeout_s
        while not job.done():
            marks = list(decoding)  # one look: the worker appends to it
            if len(marks) == 1:  # decoding: the clock stands, looked at again within the deadline's length
                left = min(DISCONNECT_POLL_S, timeout_s)
            else:
                paused = marks[1] - marks[0] if marks else 0.0
                left = submitted + paused + timeout_s - time.perf_counter()
                if left <= 0:
                    self._drop(job, cancellation)
                    raise DeadlineExceededError(timeout_s)
            await asyncio.wait({job}, timeout=min(left, DISCONNECT_POLL_S) if disconnected else left)
            if not job.done() and disconnected is not None and await disconnected():
                self._drop(job, cancellation)
                raise ClientDisconnect
        return job.result(), 1000 * (started[0] - submitted)

    @staticmethod
    def _drop(job: asyncio.Future, cancellation: Cancellation) -> None:
        """Nobody waits for the job any more: dequeue it, or stop it at its next network call
        (:mod:`service.cancellation`), which frees its worker and its slot. ``job``, the job's future in the event
        loop, is cancelled too, so that the job's exception is never handed to it (asyncio would report it, unread)."""
        job.cancel()  # cancels the worker's future as well: dequeued if it has not started
        cancellation.cancel()

    def release(self) -> None:
        if self._released:
            return
        self._released = True
        if self._future is None:
            self._limiter._release()
        else:  # runs now if the job is done, else when the worker finishes it
            self._future.add_done_callback(lambda _: self._limiter._release())
