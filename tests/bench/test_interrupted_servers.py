"""A benchmark interrupted (SIGTERM, or Ctrl-C's SIGINT sent to it alone) stops the servers it started: none is left
running, whether it was still starting them or already measuring."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[2]


def _servers_of(pid: int) -> list[int]:
    """The PIDs of the ``run_server`` processes whose parent is ``pid``."""
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            parent = int(stat.read_text().rsplit(")", 1)[1].split()[1])
            if parent == pid and b"run_server" in (stat.parent / "cmdline").read_bytes():
                found.append(int(stat.parent.name))
        except (OSError, IndexError, ValueError):  # a process that ended while being read
            continue
    return found


def _alive(pid: int) -> bool:
    """Whether ``pid`` runs (a zombie, ended and waiting to be reaped, does not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return False


def _as_from_a_shell(module: str, *args: str) -> list[str]:
    """``python -m module args`` with Ctrl-C's SIGINT raising KeyboardInterrupt, as an interactive shell starts it: a
    process inherits an ignored or blocked SIGINT (a suite started in the background by ``sh -c '... &'`` runs with
    SIGINT ignored), which would make the signal a no-op."""
    start = ("import runpy, signal, sys; signal.pthread_sigmask(signal.SIG_UNBLOCK, [signal.SIGINT]); "
             "signal.signal(signal.SIGINT, signal.default_int_handler); "
             f"sys.argv = [{module!r}, *sys.argv[1:]]; "
             f"runpy.run_module({module!r}, run_name='__main__', alter_sys=True)")
    return [sys.executable, "-c", start, *args]


def _signal_state(pid: int) -> str:
    """The ignored and blocked signal masks of ``pid`` (``/proc``), for a failure's message."""
    try:
        return " ".join(line for line in Path(f"/proc/{pid}/status").read_text().splitlines()
                        if line.startswith(("SigIgn", "SigBlk")))
    except OSError:
        return "ended"


def _interrupted(command: list[str], signum: int, ready_line: bool, tmp_path: Path) -> tuple[int, str, list[int]]:
    """Start ``command``, wait for its server (its first stdout line with ``ready_line``, else the server's process
    appearing), send it ``signum``: its exit status, its stderr and the servers it had started that still run."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    err = tmp_path / "stderr.txt"
    with err.open("w") as stderr:
        bench = subprocess.Popen(command, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=stderr, text=True)
    servers: list[int] = []
    try:
        deadline = time.time() + 120
        if ready_line:
            servers = [int(bench.stdout.readline())]  # the server's pid, printed once it answers
        while not servers and time.time() < deadline and bench.poll() is None:
            servers = _servers_of(bench.pid)
            time.sleep(0.05)
        assert servers, "the benchmark started no server"
        state = _signal_state(bench.pid)
        bench.send_signal(signum)
        status = bench.wait(timeout=60)
        time.sleep(0.5)  # a server it left behind would still be starting or serving
        return status, err.read_text() + f"\n[signal masks when signalled: {state}]", [p for p in servers if _alive(p)]
    finally:
        bench.kill()
        for pid in servers:  # ours: a leaked one must not outlive the test
            if _alive(pid):
                os.kill(pid, signal.SIGKILL)


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_real_scans_interrupted_while_its_server_starts_leaves_no_server(signum, tmp_path):
    # enough pairs that the run cannot end before the signal even where a loaded machine delays this test
    rng = np.random.default_rng(0)
    scans = tmp_path / "scans"
    scans.mkdir()
    for i in range(40):
        cloud = rng.normal(size=(2000, 3)).astype(np.float32)
        np.savez(scans / f"p{i:02d}.npz", source=cloud, target=cloud, transform=np.eye(4), sensor="cyberware-range")
    status, stderr, left = _interrupted(_as_from_a_shell("bench.real_scans", str(scans), "--no-fpfh", "--scales", "1"),
                                        signum, False, tmp_path)
    assert left == [], f"servers left running: {left}"
    if signum == signal.SIGTERM:
        assert status == 128 + signal.SIGTERM and "Traceback" not in stderr, (status, stderr[-2000:])
    else:
        assert status == -signal.SIGINT, (status, stderr[-2000:])


def test_sigterm_while_measuring_stops_the_server(tmp_path):
    script = ("import time\nfrom bench.http_latency import Server\n"
              "with Server(models='general') as server:\n"
              "    print(server.proc.pid, flush=True)\n"
              "    time.sleep(300)\n")
    status, stderr, left = _interrupted([sys.executable, "-c", script], signal.SIGTERM, True, tmp_path)
    assert left == [] and status == 128 + signal.SIGTERM and "Traceback" not in stderr


SIGNAL_IN_A_FINALIZER = """
import os, signal, sys, time
from bench import http_latency
signal.pthread_sigmask(signal.SIG_UNBLOCK, [signal.SIGINT])  # as an interactive shell starts it (_as_from_a_shell)
signal.signal(signal.SIGINT, signal.default_int_handler)
http_latency._catch_sigterm()  # as a server's start does
class Finalized:
    def __del__(self):  # Python runs the handler here and only prints what it raises
        os.kill(os.getpid(), signal.{name})
        time.sleep(0.2)
Finalized()
time.sleep(3)
print("ran on", flush=True)
"""


@pytest.mark.parametrize("signum", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_signal_handled_inside_a_finalizer_still_stops_the_benchmark(signum: int) -> None:
    """A signal whose handler runs inside a finalizer or an import's weakref callback (the first ``httpx.Client``
    imports some 130 modules while a server starts) is not lost: the benchmark stops as it would anywhere else."""
    script = SIGNAL_IN_A_FINALIZER.format(name=signal.Signals(signum).name)
    done = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=60)
    assert "ran on" not in done.stdout, done.stderr[-2000:]
    expected = 128 + signal.SIGTERM if signum == signal.SIGTERM else -signal.SIGINT  # Ctrl-C: Python ends by SIGINT
    assert done.returncode == expected, (done.returncode, done.stderr[-2000:])
