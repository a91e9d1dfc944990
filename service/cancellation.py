"""Stopping a registration nobody waits for any more: its HTTP deadline has passed (504) or its client has gone.

Python cannot interrupt an ONNX Runtime call; its ``RunOptions.terminate`` can: set from any thread, it ends the call
running with those options at its next node, and every later call with them at once. A :class:`Cancellation` holds
one ``RunOptions`` per request. While it is current (:func:`cancellable`, a context variable, so work that a
registration hands to a helper thread with ``contextvars.copy_context`` carries it along), every network call passes
its options (:func:`service.bounded_runs.run_cancellable`), and after :meth:`Cancellation.cancel` the registration stops
with :class:`RegistrationCancelledError` at its next network call: its worker and its limiter slot are free again
instead of running to the end. Outside a request (the CLI, the library) nothing is current and calls run as before.
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from typing import TYPE_CHECKING

if TYPE_CHECKING:  # loaded with the first Cancellation: the file formats check cancelled() without ONNX Runtime
    import onnxruntime as ort


class RegistrationCancelledError(Exception):
    """The registration was cancelled (its request's deadline passed); nobody reads its result."""


class Cancellation:
    """The cancellation of one request's registration, settable from any thread."""

    def __init__(self) -> None:
        import onnxruntime as ort

        self.run_options = ort.RunOptions()
        self._cancelled = threading.Event()

    @property
    def cancelled(self) -> bool:
        return self._cancelled.is_set()

    def cancel(self) -> None:
        """Stop the registration: a network call running with :attr:`run_options` ends at its next node, and the
        registration raises :class:`RegistrationCancelledError` at its next network call."""
        self._cancelled.set()
        self.run_options.terminate = True


_current: ContextVar[Cancellation | None] = ContextVar("mfgnet_cancellation", default=None)


@contextmanager
def cancellable(cancellation: Cancellation) -> Iterator[None]:
    """``cancellation`` current in the calling context while the block runs."""
    token = _current.set(cancellation)
    try:
        yield
    finally:
        _current.reset(token)


def run_options() -> ort.RunOptions | None:
    """The current cancellation's ``RunOptions`` for a network call (``None`` outside a request), or
    :class:`RegistrationCancelledError` where it was cancelled already."""
    cancellation = _current.get()
    if cancellation is None:
        return None
    if cancellation.cancelled:
        raise RegistrationCancelledError
    return cancellation.run_options


def stop_if_cancelled() -> None:
    """:class:`RegistrationCancelledError` where the current cancellation was cancelled: long work between network
    calls (an aligned download's file, written a block at a time) stops at its next block."""
    if cancelled():
        raise RegistrationCancelledError


def cancelled() -> bool:
    """Whether the current cancellation was cancelled (a network call's failure is then its termination, not an
    error of the model)."""
    cancellation = _current.get()
    return cancellation is not None and cancellation.cancelled
