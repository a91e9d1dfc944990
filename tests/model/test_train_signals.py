"""`mfgnet train` stops cleanly on SIGTERM / SIGINT: the step finishes, last.pt is written, --resume goes on."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from tiny_training import TINY_MODEL, tiny_training_data

from model.checkpoint import read_checkpoint
from model.graceful_stop import GracefulStop

TRAIN = f"""
import sys
from model.train import TrainOptions, run_training
opts = TrainOptions(setting="resampled", out=sys.argv[1], data=sys.argv[2], epochs=int(sys.argv[3]), batch_size=2,
                    val_pairs=2, device="cpu", threads=1, config={TINY_MODEL}, checkpoint_minutes=60.0,
                    resume=sys.argv[4] == "resume")
outcome = run_training(opts)
print("best", outcome.best, "stopped by", outcome.stopped_by, flush=True)
"""


def start_training(run: Path, data: str, epochs: int, resume: bool) -> subprocess.Popen:
    return subprocess.Popen(
        [sys.executable, "-c", TRAIN, str(run), data, str(epochs), "resume" if resume else "fresh"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )


def read_until(proc: subprocess.Popen, marker: str, timeout: float) -> str:
    """Output of ``proc`` up to and including the first line holding ``marker`` (fails after ``timeout`` s)."""
    seen: list[str] = []
    found = threading.Event()

    def reader() -> None:
        for line in proc.stdout:
            seen.append(line)
            if marker in line:
                found.set()
                return

    threading.Thread(target=reader, daemon=True).start()
    if not found.wait(timeout):
        proc.kill()
        pytest.fail(f"no {marker!r} within {timeout} s; output:\n{''.join(seen)}")
    return "".join(seen)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_signal_checkpoints_the_run_and_resume_continues_it(tmp_path, sig) -> None:
    """Either signal stops the run with last.pt where the log stops; after SIGTERM, --resume runs on from it."""
    data = tiny_training_data(tmp_path)
    run = tmp_path / "run"
    proc = start_training(run, data, epochs=1000, resume=False)
    read_until(proc, '"epoch": 1,', timeout=120)  # two epochs logged: the loop is running
    proc.send_signal(sig)
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 0, out
    assert f"stopped on {sig.name}" in out and "--resume continues there" in out
    assert f"stopped by {sig.name}" in out  # a run cut short says so (`mfgnet train` exits 128 + the signal)
    state = read_checkpoint(run / "last.pt")["state"]
    logged = len((run / "log.jsonl").read_text().splitlines())
    assert state["epoch"] == logged >= 2  # the checkpoint is where the log stops (inside an epoch: at its batch)
    if sig is signal.SIGINT:
        return  # the stop is the same for both signals: resuming it is checked once, after SIGTERM

    resumed = start_training(run, data, epochs=state["epoch"] + 1, resume=True)
    out, _ = resumed.communicate(timeout=180)
    assert resumed.returncode == 0, out
    assert f"resumed from {run / 'last.pt'} at epoch {state['epoch']} batch {state['batch']}" in out
    assert "stopped by None" in out  # it ran to its end
    records = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert [r["epoch"] for r in records] == list(range(state["epoch"] + 1))  # nothing lost, nothing repeated


def test_graceful_stop_restores_the_handlers_and_a_second_signal_stops_at_once() -> None:
    before = signal.getsignal(signal.SIGTERM)
    with GracefulStop() as stop:
        os.kill(os.getpid(), signal.SIGTERM)
        time.sleep(0.01)  # the handler runs between bytecodes of this thread
        assert stop.requested == "SIGTERM"
        with pytest.raises(KeyboardInterrupt, match="second SIGTERM"):
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(0.01)
    assert signal.getsignal(signal.SIGTERM) is before


def test_graceful_stop_outside_the_main_thread_leaves_the_signals_alone() -> None:
    seen: dict[str, object] = {}

    def in_thread() -> None:
        with GracefulStop() as stop:
            seen["handler"] = signal.getsignal(signal.SIGTERM)
            seen["requested"] = stop.requested

    thread = threading.Thread(target=in_thread)
    thread.start()
    thread.join()
    assert seen == {"handler": signal.getsignal(signal.SIGTERM), "requested": None}
