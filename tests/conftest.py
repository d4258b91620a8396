"""Shared by every test module. The project's BLAS setting (one thread per process, see
``protocol/__init__``) must precede numpy, which test modules import first."""
import protocol  # noqa: F401
