"""The geometry of a painting's tiles, apart from their registration (:mod:`uvps.core.mosaic`).

``uvps batch --mosaic`` checks its layout (every tile overlaps another) before it starts its cluster; this
module imports nothing, so that the check does not import scipy and numba (0.7 s on one core, ``python
-X importtime -c "import uvps.core.mosaic"``) ahead of the workers' start.
"""
from __future__ import annotations

from typing import Optional


def overlap_box(ca, shape_a, cb, shape_b) -> Optional[tuple]:
    """``(x_lo, y_lo, x_hi, y_hi)`` of two tiles' overlap in painting pixels, or None.

    ``ca``, ``cb``: the tiles' corners ``(x, y)`` in painting pixels; ``shape_a``, ``shape_b``: their
    ``(rows, columns)``.
    """
    x_lo, y_lo = max(ca[0], cb[0]), max(ca[1], cb[1])
    x_hi, y_hi = min(ca[0] + shape_a[1], cb[0] + shape_b[1]), min(ca[1] + shape_a[0], cb[1] + shape_b[0])
    return (x_lo, y_lo, x_hi, y_hi) if x_hi > x_lo and y_hi > y_lo else None
