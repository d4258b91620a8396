"""The wire: Zenoh keys, typed messages with a validating msgpack codec, session config.

Importing any of the project's packages imports this one first, which limits the BLAS under
numpy and scipy to one thread per process unless the environment says otherwise: the
matrices here are small (an estimator's tens of rows), many of the project's processes share
a host, and OpenBLAS's idle threads spin (4% of the test suite's CPU before this). It acts
only if numpy is not yet imported; child processes inherit it.
"""
import os

if not {"OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS"} & os.environ.keys():
    os.environ["OPENBLAS_NUM_THREADS"] = "1"
