"""ONNX Runtime calls whose memory stays bounded whatever batch and sizes a request asks for.

By default ONNX Runtime gives each session its own CPU arena and keeps it at the largest call that session has run;
a model holds one matcher session per iteration. A request at the options' limits (512 keypoints, 8 iterations,
the rotation search with `refine: "none"`, which runs four hypotheses per call on the full working clouds) grew
the process by about 2.8 GB and kept it: above a deployment's memory limit, from one request. So every session of
the process allocates from one shared arena (:func:`share_one_cpu_arena`), and :func:`run_bounded` splits a call
along its batch so that each part fits a budget: the largest call of a request within the defaults, so those run
exactly as one call. The arena then grows to about what the largest part needs once per call running at the same
time, and no further.
"""

from __future__ import annotations

import threading

import numpy as np
import onnxruntime as ort

from service.cancellation import RegistrationCancelledError, cancelled, run_options

# Keypoint pairs (B x K x L) per matcher call: the rotation search of `refine: "none"` at the default keypoints
# (four hypotheses of 128 x 128); the defaults' own largest call is one pair of 128 x 128.
MATCH_PAIRS_PER_CALL = 4 * 128 * 128
# Points (B x N) per encoder call: the plain pass at the largest working size (source and target of 4096).
ENCODE_POINTS_PER_CALL = 2 * 4096

_arena_lock = threading.Lock()
_arena_registered = False


def share_one_cpu_arena(options: ort.SessionOptions) -> ort.SessionOptions:
    """``options`` for a session that allocates from the process's one shared CPU arena (registered with ONNX
    Runtime's environment at the first call)."""
    global _arena_registered
    with _arena_lock:
        if not _arena_registered:
            cpu = ort.OrtMemoryInfo("Cpu", ort.OrtAllocatorType.ORT_ARENA_ALLOCATOR, 0, ort.OrtMemType.DEFAULT)
            ort.create_and_register_allocator(cpu, ort.OrtArenaCfg(0, -1, -1, -1))  # ORT's default arena settings
            _arena_registered = True
    options.add_session_config_entry("session.use_env_allocators", "1")
    return options


def run_bounded(session: ort.InferenceSession, feeds: dict[str, np.ndarray], row_cost: int,
                budget: int) -> list[np.ndarray]:
    """``session.run`` of ``feeds`` (every input ``[B, ...]``): one call when ``B * row_cost <= budget``, else
    slices of ``max(1, budget // row_cost)`` rows, their outputs (each ``[B, ...]``) joined along the batch."""
    rows = len(next(iter(feeds.values())))
    if rows * row_cost <= budget:
        return run_cancellable(session, feeds)
    step = max(1, budget // row_cost)
    parts = [run_cancellable(session, {name: value[first : first + step] for name, value in feeds.items()})
             for first in range(0, rows, step)]
    return [np.concatenate(outputs) for outputs in zip(*parts, strict=True)]


def run_cancellable(session: ort.InferenceSession, feeds: dict[str, np.ndarray]) -> list[np.ndarray]:
    """``session.run`` with the current request's ``RunOptions`` (:mod:`service.cancellation`): a cancelled
    request's call ends with :class:`service.cancellation.RegistrationCancelledError`."""
    options = run_options()
    try:
        return session.run(None, feeds, options)
    except Exception:
        if cancelled():  # ONNX Runtime's error was the termination asked for
            raise RegistrationCancelledError from None
        raise
