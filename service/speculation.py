"""Work started ahead on a spare core: a registration's rotation search run beside its plain pass.

``rotation_search="auto"`` searches only after the plain pass (network, refinement, slide check, assessment) has
judged its pose doubtful, and on real scans at a random orientation it nearly always is. When the plain network's
pose already fits poorly, :class:`service.registrar.Registrar` starts the search in a helper thread while the plain
pass goes on, and takes its result if the plain pass asks for the search; otherwise it cancels it. The search does not
depend on the plain pass, so the result is the same either way, only sooner
(``docs/decisions/0029-the-search-started-beside-the-plain-pass.md``).

Helpers share the process's cores with the registrations: :class:`Helpers` starts one only while fewer threads are
registering or helping than it has cores, so concurrent requests, which already fill them, run as before; and the
large KD-tree queries of a registering or helping thread run on its share of the cores (:meth:`Helpers.share`).
Cancellation is cooperative: the helper's work calls :func:`check` between its stages and stops at the next one.
"""

from __future__ import annotations

import contextvars
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from typing import Any

from service.kdtree import sharing_cores


class CancelledError(Exception):
    """Raised at a :func:`check` of work whose result is no longer wanted."""


def check(cancelled: threading.Event | None) -> None:
    """Raise :class:`CancelledError` when ``cancelled`` is set (``None``: work that cannot be cancelled)."""
    if cancelled is not None and cancelled.is_set():
        raise CancelledError


class Speculation:
    """One piece of work running ahead in a helper: :meth:`result` waits for it, :meth:`cancel` drops it."""

    def __init__(self, future: Future, cancelled: threading.Event, release: Callable[[], None]):
        self._future = future
        self._cancelled = cancelled
        self._release = release  # the helper's place, when the work never ran

    def result(self) -> Any:
        """The work's return value (its exception re-raised), waiting for it to finish."""
        return self._future.result()

    def cancel(self) -> None:
        """Drop the work: not started, it never runs; running, it stops at its next :func:`check`."""
        self._cancelled.set()
        if self._future.cancel():  # it had not started and never will
            self._release()


class Helpers:
    """Helper threads for the registrations of a process, within ``cores`` threads at work at once.

    A registration counts itself while it runs (:meth:`registering`); :meth:`start` hands work to a helper only while
    the registering and helping threads are fewer than ``cores``, so a helper never competes with another request.
    """

    def __init__(self, cores: int):
        self.cores = cores
        self._busy = 0  # threads registering or helping now
        self._lock = threading.Lock()
        self._pool = ThreadPoolExecutor(max_workers=max(1, cores - 1), thread_name_prefix="mfgnet-helper")

    @property
    def busy(self) -> int:
        """Threads registering or helping now."""
        with self._lock:
            return self._busy

    def share(self) -> int:
        """The cores each busy thread may use now (at least 1): what a KD-tree query of theirs runs on
        (:func:`service.kdtree.sharing_cores`)."""
        return max(1, self.cores // max(1, self._busy))  # a read of one int: no lock needed

    @contextmanager
    def registering(self) -> Iterator[None]:
        """Count the calling thread as busy while the block runs; its KD-tree queries take its :meth:`share`."""
        with self._lock:
            self._busy += 1
        try:
            with sharing_cores(self.share):
                yield
        finally:
            self._release()

    def start(self, work: Callable[[threading.Event], Any]) -> Speculation | None:
        """``work(cancelled)`` in a helper thread, or ``None`` (nothing started) when every core is busy. ``work``
        should :func:`check` ``cancelled`` between its steps."""
        with self._lock:
            if self._busy >= self.cores:
                return None
            self._busy += 1
        cancelled = threading.Event()
        try:
            # the helper runs in the caller's context: a request's cancellation (service.cancellation) reaches it
            future = self._pool.submit(contextvars.copy_context().run, self._run, work, cancelled)
        except RuntimeError:  # the pool is shut down (interpreter exit)
            self._release()
            return None
        return Speculation(future, cancelled, self._release)

    def _run(self, work: Callable[[threading.Event], Any], cancelled: threading.Event) -> Any:
        try:
            check(cancelled)
            with sharing_cores(self.share):
                return work(cancelled)
        finally:
            self._release()

    def _release(self) -> None:
        with self._lock:
            self._busy -= 1


_shared: Helpers | None = None
_shared_lock = threading.Lock()


def shared_helpers(cores: int) -> Helpers:
    """The process's :class:`Helpers` (every model's registrations share the cores), made on first use with
    ``cores``."""
    global _shared
    with _shared_lock:
        if _shared is None:
            _shared = Helpers(cores)
        return _shared
