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


#: Pixel sizes (um) a user may give for a photograph of a painting (the paper's about 30 um per
#: pixel; a macro lens at 1:1 about 4 um; a whole 2 m painting on 2000 px 1000 um). Outside, the
#: value is almost surely in another unit (0.1 typed as mm, a size in nm, a dpi). The Fiji side
#: refuses the same range in its dialogs (``bridge_logic.PIXEL_SIZE_RANGE_UM``).
PIXEL_SIZE_RANGE_UM = (1.0, 1000.0)


def check_plausible_pixel_size(value: float, name: str = "pixel_size_um") -> float:
    """A pixel size the user typed (the command line's ``--pixel-size-um``, a request's
    ``pixel_size_um``), refused with a one-line :class:`UVPSInputError` when outside
    :data:`PIXEL_SIZE_RANGE_UM`, before any work (library functions take any positive size).

    >>> check_plausible_pixel_size(30.0)
    30.0
    >>> check_plausible_pixel_size(0.1)
    Traceback (most recent call last):
    ...
    uvps.errors.UVPSInputError: pixel_size_um 0.1 um is not a pixel size on a painting (1-1000 um); give it in micrometres (0.1 mm = 100 um)
    """
    px = check_pixel_size(value, name)
    low, high = PIXEL_SIZE_RANGE_UM
    if not low <= px <= high:
        hint = "0.1 mm = 100 um" if px < low else "a size in nm or a dpi? 300 dpi = 84.7 um"
        raise UVPSInputError(f"{name} {px:g} um is not a pixel size on a painting ({low:g}-{high:g} um); "
                             f"give it in micrometres ({hint})")
    return px

