"""One BLAS thread for the runtime's numpy work, process-wide.

The runtime's numpy products are small (the ``[K, 64] x [64, L]`` embedding distances, 3x3 and 6x6
systems), and ONNX Runtime's intra-op threads already use the cores. OpenBLAS (numpy's and scipy's) still
splits the larger products over a thread per core, and those workers then compete with ONNX Runtime and
with concurrent requests: with two registrations at once on the 2-core development VM, 22-23 instead of
29-30 registrations per second; beside a busy process one embedding distance took 15.8 ms instead of
0.24 (``docs/BENCHMARKS.md``, "BLAS threads").

OpenBLAS takes a new thread count only from the process's main thread (0.3.30 and 0.3.31 with pthreads ignore the
call from any other thread), and the count then holds for every thread. So the server sets it once, from
the thread that builds the app, before the worker threads run registrations. The container sets
``OMP_NUM_THREADS=1``, which OpenBLAS reads at load time, to the same effect.
"""

from __future__ import annotations

import threading

from threadpoolctl import ThreadpoolController


def blas_runtimes() -> list:
    """threadpoolctl's controllers of the BLAS runtimes loaded in this process now."""
    return ThreadpoolController().select(user_api="blas").lib_controllers


def blas_thread_counts() -> list[int]:
    """The thread count of every BLAS runtime loaded in this process."""
    return [lib.get_num_threads() for lib in blas_runtimes()]


def use_one_blas_thread() -> bool:
    """Set every loaded BLAS runtime to one thread for the whole process. Only the main thread can; from any
    other thread this does nothing and returns ``False``. Runtimes loaded later keep their own count."""
    if threading.current_thread() is not threading.main_thread():
        return False
    for lib in blas_runtimes():
        lib.set_num_threads(1)
    return True
