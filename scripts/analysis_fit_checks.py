#!/usr/bin/env python
"""The fit checks' quantities (``pipeline.fit_checks``) on the robustness benchmark's rows with the true
lamp positions: the normals' rms relative residual, the share of pixels without normals, the mean
normal's tilt, and the run's warnings. 300 x 400 px of 60 um (the benchmark's 18 x 24 mm field),
12 lamps, seed 0; docs/decisions/normals.md, "Fit-check thresholds".

Example::

    .venv/bin/python scripts/analysis_fit_checks.py            # every row
    .venv/bin/python scripts/analysis_fit_checks.py all beams
"""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from benchmark_robustness import ROWS, spec_for  # noqa: E402

from uvps.core.pipeline import RunOptions, run  # noqa: E402
from uvps.testing.synthetic import make_capture  # noqa: E402


def main(rows) -> int:
    print("| row | residual (rms, relative) | pixels without normals | mean tilt (deg) | warnings |")
    print("|---|---|---|---|---|")
    for row in rows or ROWS:
        cap = make_capture(spec_for(row, shape=(300, 400), pixel_size_um=60.0, seed=0, n_lights=12))
        res = run(cap.as_capture(lights="positions"), RunOptions(), stages=("normals",))
        d = res.diagnostics["normals"]
        print(f"| {row} | {d['residual_rms']:.4f} | {100 * d['invalid_fraction']:.1f} % | {d['mean_tilt_deg']:.2f} | "
              f"{len(res.warnings)} |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
