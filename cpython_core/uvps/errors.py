"""Exceptions of uvps.

Bad input (a file, a parameter) raises :class:`UVPSInputError` with a one-line message naming the
file or parameter and what was expected; the CLI and the bridge exit with status 1. A failure while
computing on valid input raises :class:`UVPSComputeError` (exit status 2).
"""


class UVPSError(Exception):
    """Base class of uvps errors."""

    exit_code = 2


class UVPSInputError(UVPSError, ValueError):
    """Bad input: a file, a light file, a mask or a parameter. Exit status 1."""

    exit_code = 1


class UVPSComputeError(UVPSError, RuntimeError):
    """The computation failed on input that looked valid. Exit status 2."""

    exit_code = 2
