"""The wire: Zenoh keys, typed messages with a validating msgpack codec, session config.

Importing any of the project's packages imports this one first, which sets two things about
the process:

- The BLAS under numpy and scipy gets one thread per process unless the environment says
  otherwise: the matrices here are small (an estimator's tens of rows), many of the project's
  processes share a host, and OpenBLAS's idle threads spin (4% of the test suite's CPU before
  this). It acts only if numpy is not yet imported; child processes inherit it.
- glibc's allocator keeps freed blocks of up to :data:`KEPT_BLOCK` bytes for reuse, unless
  the environment tunes it (``MALLOC_*_`` or ``GLIBC_TUNABLES``). By default glibc maps a block
  over ~128 KiB afresh from the kernel and unmaps it when freed, so every such numpy temporary
  (``ekf``'s bank of 180 filters is 370 KB a covariance) pays its page faults again: 4x the
  arithmetic of a Kalman update (docs/benchmarks.md). Elsewhere (another libc) it does nothing.
"""
import ctypes
import os
import sys

if not {"OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"} & os.environ.keys():
    os.environ["OPENBLAS_NUM_THREADS"] = "1"

KEPT_BLOCK = 32 << 20  # glibc's ceiling for M_MMAP_THRESHOLD on 64-bit hosts
M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # mallopt's parameters (<malloc.h>)


def _keep_freed_blocks() -> None:
    """Raise glibc's mmap threshold to :data:`KEPT_BLOCK` (and the heap's trim threshold to
    twice it, as glibc's own dynamic rule pairs them), so blocks below it are served from and
    returned to the heap (see the module docstring)."""
    if not sys.platform.startswith("linux") or "GLIBC_TUNABLES" in os.environ or any(
            key.startswith("MALLOC_") and key.endswith("_") for key in os.environ):
        return
    try:
        mallopt = ctypes.CDLL(None).mallopt
    except (OSError, AttributeError):  # not glibc (musl has no mallopt)
        return
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    mallopt(M_MMAP_THRESHOLD, KEPT_BLOCK)
    mallopt(M_TRIM_THRESHOLD, 2 * KEPT_BLOCK)


_keep_freed_blocks()
