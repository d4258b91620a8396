import protocol  # noqa: F401  (first: one BLAS thread per process, see protocol/__init__)
