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


def in_chain(exc: BaseException, kind):
    """The exception of type ``kind`` that ``exc`` is or wraps (down its ``__cause__`` /
    ``__context__`` chain), else None. A signal's exception raised inside a compiled (numba) kernel
    reaches Python as a ``SystemError`` ("returned a result with an exception set") with it down
    the chain: the CLI's Ctrl-C and the bridge's cancellation look for it there.

    >>> try:
    ...     try:
    ...         raise KeyboardInterrupt
    ...     except KeyboardInterrupt as inner:
    ...         raise SystemError("kernel") from inner
    ... except SystemError as exc:
    ...     type(in_chain(exc, KeyboardInterrupt)).__name__, in_chain(exc, ValueError)
    ('KeyboardInterrupt', None)
    """
    seen = set()
    while exc is not None and id(exc) not in seen:
        if isinstance(exc, kind):
            return exc
        seen.add(id(exc))
        exc = exc.__cause__ or exc.__context__
    return None


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
