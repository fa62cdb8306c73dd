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


def check_pixel_size(value, name: str = "pixel_size_um") -> float:
    """``value`` as a positive, finite pixel size in micrometres, else a one-line
    :class:`UVPSInputError` naming ``name``: the one check of a pixel size in uvps.

    >>> check_pixel_size("15")
    15.0
    >>> check_pixel_size(0)
    Traceback (most recent call last):
    ...
    uvps.errors.UVPSInputError: pixel_size_um must be a positive number (micrometres); got 0
    """
    try:
        px = float(value)
    except (TypeError, ValueError):
        px = float("nan")
    if isinstance(value, bool) or not (px == px and px > 0 and px != float("inf")):
        raise UVPSInputError(f"{name} must be a positive number (micrometres); got {value!r}")
    return px
