"""Stop a training run cleanly on SIGTERM or SIGINT: finish the step, checkpoint, return (``--resume`` continues).

Without it ``kill <pid>`` (or Ctrl-C) lost everything since the last periodic checkpoint. The first signal only sets
:attr:`GracefulStop.requested`; the training loop checks it after each step. A second signal stops at once
(``KeyboardInterrupt``), for a run that hangs.
"""

from __future__ import annotations

import signal
import threading
from types import FrameType

SIGNALS = (signal.SIGTERM, signal.SIGINT)


class GracefulStop:
    """Context manager: while active, SIGTERM / SIGINT request a stop instead of killing the process.

    Handlers can only be installed from the main thread; elsewhere (a training call inside a worker thread) the
    signals keep their handlers and :attr:`requested` stays ``None``.
    """

    def __init__(self) -> None:
        self.requested: str | None = None  # name of the signal that asked for the stop
        self._previous: dict[int, object] = {}

    def __enter__(self) -> GracefulStop:
        if threading.current_thread() is threading.main_thread():
            self._previous = {sig: signal.signal(sig, self._handle) for sig in SIGNALS}
        return self

    def __exit__(self, *exc_info) -> None:
        for sig, handler in self._previous.items():
            signal.signal(sig, handler)
        self._previous = {}

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        if self.requested is not None:
            raise KeyboardInterrupt(f"second {signal.Signals(signum).name}: stopping without a checkpoint")
        self.requested = signal.Signals(signum).name
        print(f"{self.requested}: stopping after this step with a checkpoint (send it again to stop at once)",
              flush=True)
