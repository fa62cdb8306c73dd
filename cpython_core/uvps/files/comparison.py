"""``comparison.csv``: two detections compared per colour area (:mod:`uvps.core.compare`), written
atomically and read back."""
from __future__ import annotations

import csv
from pathlib import Path

from ..core.compare import COLUMNS as COMPARISON_COLUMNS, Comparison
from ..errors import UVPSInputError
from .tables import atomic_write_text, table_to_csv_text


def write_comparison_csv(path, comparison: Comparison) -> None:
    """Write ``comparison.csv`` atomically: a row per area, then "all".

    Columns :data:`uvps.core.compare.COLUMNS`, then ``table_a`` and ``table_b`` (what the two tables are, e.g. the
    file names ``protrusions_manual`` and ``protrusions``), so the file describes itself.
    """
    cols = {c: [r[c] for r in comparison.rows] for c in COMPARISON_COLUMNS}
    cols["table_a"] = [comparison.name_a] * len(comparison.rows)
    cols["table_b"] = [comparison.name_b] * len(comparison.rows)
    atomic_write_text(path, table_to_csv_text(cols, list(cols)))


def read_comparison_csv(path) -> list:
    """Read ``comparison.csv`` back as a list of row dicts (strings)."""
    path = Path(path)
    if not path.is_file():
        raise UVPSInputError(f"comparison table {path} does not exist")
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    if rows and not set(COMPARISON_COLUMNS) <= set(rows[0]):
        raise UVPSInputError(f"comparison table {path}: expected columns {','.join(COMPARISON_COLUMNS)}")
    return rows
