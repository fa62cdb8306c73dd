"""A capture in memory, and the stacks the stages read it through.

:class:`Capture` holds K images of one field of view, one per lamp. Its ``images`` are an array or a
lazy stack (:class:`LazyStack`): a memory-mapped folder of TIFFs (:class:`uvps.files.io.MappedStack`)
or a view that corrects on access (:class:`StackView`: the additive term, lamp beams, a card's
gains). What a stage may do with a lazy stack is written once in :class:`LazyStack` and
docs/architecture.md, "Lazy stacks".
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional, Protocol, runtime_checkable

import numpy as np


@runtime_checkable
class Stack(Protocol):
    """What a stage may use of ``Capture.images``: a ``(K, M, N[, C])`` numpy array or a
    :class:`LazyStack` (docs/architecture.md, "Lazy stacks"). Indexing reads a part (``[k]``,
    ``[k, rows, cols]``, ``[:, rows, cols]``, ``[:, r, c]``); the whole stack is :func:`load`."""

    shape: tuple
    ndim: int
    dtype: np.dtype

    def __len__(self) -> int: ...

    def __getitem__(self, key) -> np.ndarray: ...


def load(stack: Stack) -> np.ndarray:
    """The whole stack as one array in memory: the one explicit full load (an array is returned as is)."""
    return stack if isinstance(stack, np.ndarray) else stack.load()


@dataclass
class Capture:
    """A capture: K images of one field of view, one per light.

    Attributes
    ----------
    images : ndarray or LazyStack
        ``(K, M, N)`` or ``(K, M, N, 3)``, linear, dark-subtracted, NEVER rescaled: the files' own
        counts (uint16 0..65535, uint8 0..255). Integer files keep their dtype; a dark frame or
        sRGB linearisation gives float32. A folder of uncompressed TIFFs is memory-mapped
        (:class:`uvps.files.io.MappedStack`), and later stages may wrap the stack in a view that corrects on
        access (:class:`StackView`: additive term, lamp beams): index it, or ``np.asarray`` it for
        the whole stack in memory.
    files : list of str
        One per image; an image of a multi-page stack is ``"/path/stack.tif#k"`` with k from 1 (the
        ImageJ slice number).
    pixel_size_um : float
        Size of a pixel on the painting, micrometres.
    mask : ndarray or None
        ``(M, N)`` bool, True = use.
    saturation : float or None
        Counts at/above which a sample is saturated (dtype max); None for float input.
    light_directions : ndarray or None
        ``(K, 3)`` unit vectors toward the lights (world frame), from an ``.lp`` file.
    light_positions_mm : ndarray or None
        ``(K, 3)`` light positions in mm from the image centre, from a positions file.
    bit_depth : str
        The files' dtype, e.g. ``"uint16"``.
    light_intensities : ndarray or None
        ``(K,)`` relative lamp intensities ``E_k`` (> 0) when the light file gives them (an ``.lp``
        4th column, a positions CSV ``intensity`` column, ``lights.json`` ``intensity``); None when
        it does not.
    raw : dict or None
        Camera raw files (:data:`uvps.files.io.RAW_EXTS`): how they were read (:func:`uvps.files.io.raw_reading`: the black and
        white levels subtracted, white balance, demosaic), recorded in ``run.json``; None otherwise.
    """

    images: np.ndarray
    files: list
    pixel_size_um: float
    mask: Optional[np.ndarray]
    saturation: Optional[float]
    light_directions: Optional[np.ndarray]
    light_positions_mm: Optional[np.ndarray]
    bit_depth: str
    light_intensities: Optional[np.ndarray] = None
    raw: Optional[dict] = None          # camera raw files: how LibRaw read them (:func:`uvps.files.io.read_raw`)


class LazyStack:
    """A ``(K, M, N[, C])`` stack that yields arrays only when indexed: the protocol every stage
    reads a capture through (docs/architecture.md, "Lazy stacks").

    A stage may use ``shape``, ``ndim``, ``dtype`` (set by subclasses), ``len()``, iteration (one
    image at a time) and indexing that reads a part (``[k]``, ``[k, rows, cols]``,
    ``[:, rows, cols]``, ``[:, r, c]`` with two index arrays of one shape; subclasses implement
    ``__getitem__``). The whole stack in memory is one explicit call, :meth:`load`
    (``np.asarray(stack)`` is numpy's spelling of it).
    """

    def __len__(self):
        return self.shape[0]

    def __iter__(self):
        for k in range(self.shape[0]):
            yield self[k]

    def load(self) -> np.ndarray:
        """The whole stack as one array in memory (every image read)."""
        return self[:]

    def __array__(self, dtype=None, copy=None):
        out = self.load()
        return out if dtype is None else out.astype(dtype)


class StackView(LazyStack):
    """A capture's stack seen through a correction computed on access (the stack is never copied).

    Subclasses implement :meth:`correct`: given the float32 values indexed by ``(k, rows, cols)``
    (each an int, a slice or an index array, as the stages use them: ``[k]``, ``[k, rows, cols]``,
    ``[:, rows, cols]``, ``[:, r, c]`` with two index arrays of one shape), return them corrected.
    Views nest (a gain-corrected view of an offset-corrected one).
    """

    def __init__(self, images):
        self.base = images
        self.shape = images.shape
        self.ndim = images.ndim
        self.dtype = np.dtype(np.float32)

    def __getitem__(self, key):
        key = key if isinstance(key, tuple) else (key,)
        if len(key) > 3:
            raise IndexError(f"{type(self).__name__} takes at most (image, row, col) indices")
        key = key + (slice(None),) * (3 - len(key))
        return self.correct(np.asarray(self.base[key], dtype=np.float32), *key)

    def correct(self, values, kk, rk, ck):  # pragma: no cover - abstract
        raise NotImplementedError

    def release_caches(self) -> None:
        """Drop what this view and the views under it keep to be read faster (made again if the stack
        is read again): called once the stages that read the stack are done."""
        release_caches(self.base)

    def raw_parts(self, k: int, rows: slice, cols: slice) -> Optional["RawParts"]:
        """The band as stored and this view's correction as :class:`RawParts`, or None when the
        correction is not one of theirs (a view that is no dark frame or gain map says None)."""
        return None


@dataclass
class RawParts:
    """One image's band as stored and the corrections the views over it apply on access, for a
    compiled kernel that applies them as it reads each sample (:func:`uvps.core.offset.block_stats_parts`)
    instead of making the corrected float32 band first (a copy of the band in the files' dtype, its
    float32 conversion, the dark frame's subtraction and the gain's division: four passes and three
    temporaries of the band). The value a view yields is, in float32 as the views compute it,
    ``max(float32(raw) - dark, 0) * factor`` (each term only when given).

    Attributes
    ----------
    raw : ndarray, (m, n) or (m, n, C)
        The band as stored (a memory-mapped file's view, not copied), in this machine's byte order.
    dark : ndarray like ``raw`` (float32, or integer counts as stored), or None
        A dark frame subtracted, clipped at 0 (:class:`uvps.files.io.DarkSubtracted`).
    factor : ndarray of float32, (m, n), or None
        A factor multiplied: 1 / a lamp's gain map (:class:`uvps.core.flatfield.GainCorrected`).
    done : callable
        Called once the band is read (a mapped file's pages are released from the resident set).
    """

    raw: np.ndarray
    dark: Optional[np.ndarray] = None
    factor: Optional[np.ndarray] = None
    done: Callable = lambda: None


def release_caches(stack) -> None:
    """:meth:`StackView.release_caches` of a view; nothing for an array or a lazy stack without one."""
    f = getattr(stack, "release_caches", None)
    if f is not None:
        f()


def raw_parts(stack, k: int, rows: slice, cols: slice) -> Optional[RawParts]:
    """Image ``k``'s band ``rows`` x ``cols`` of ``stack`` as :class:`RawParts`: a numpy array in native
    byte order as it is, a lazy stack by its own ``raw_parts`` (memory-mapped files, a dark frame, a gain
    map); None for anything else (the band is then read by indexing)."""
    if isinstance(stack, np.ndarray):
        return RawParts(stack[k, rows, cols]) if stack.dtype.isnative else None
    f = getattr(stack, "raw_parts", None)
    return None if f is None else f(k, rows, cols)


def float_band(stack, rows: slice) -> np.ndarray:
    """``stack[:, rows]`` (every image's band of rows) as float32, as ``np.asarray(stack[:, rows], np.float32)``
    gives it: memory-mapped files (a lazy stack that is no :class:`StackView`, whose :func:`raw_parts` are the
    stored band alone) converted straight from the files into the float32 band, one pass, instead of a copy per
    image, their stack and its conversion (the same values: integers convert to float32 exactly, and a float32
    file is copied). Anything else is indexed."""
    if isinstance(stack, (np.ndarray, StackView)):
        return np.asarray(stack[:, rows], dtype=np.float32)
    parts = [raw_parts(stack, k, rows, slice(None)) for k in range(stack.shape[0])]
    if not parts or any(p is None or p.dark is not None or p.factor is not None
                        or not np.can_cast(p.raw.dtype, np.float32, casting="safe") for p in parts):
        for p in parts:
            if p is not None:
                p.done()
        return np.asarray(stack[:, rows], dtype=np.float32)
    out = np.empty((len(parts),) + parts[0].raw.shape, np.float32)
    for k, p in enumerate(parts):
        np.copyto(out[k], p.raw, casting="safe")
        p.done()
    return out


def row_bands(n_rows: int, row_cost: int, budget: int) -> list:
    """Row slices covering ``n_rows`` rows, each of at most ``budget`` (at least one row), a row
    costing ``row_cost`` (pixels or bytes): how every band-by-band step cuts an image."""
    step = max(1, int(budget) // max(int(row_cost), 1))
    return [slice(r0, min(n_rows, r0 + step)) for r0 in range(0, n_rows, step)]
