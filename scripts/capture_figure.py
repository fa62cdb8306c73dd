#!/usr/bin/env python
"""The picture of docs/capture.md: a synthetic sphere capture (a matte white sphere on a stand and a
glossy black one, under the lamps of a synthetic painting capture) and what ``uvps calibrate`` found.

    .venv/bin/python scripts/capture_figure.py docs/images/capture_spheres.png
"""
from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from uvps.commands import COMMANDS  # noqa: E402
from uvps.testing.synthetic import make_capture  # noqa: E402
from uvps.testing.synthetic_spheres import SphereSpec, make_sphere_capture, write_sphere_capture  # noqa: E402


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    out = Path(argv[0] if argv else "docs/images/capture_spheres.png")
    cap = make_capture(shape=(450, 600), n_lights=8, seed=5, pixel_size_um=40.0, rgb=False, black_level=200.0)
    sc = make_sphere_capture(cap, [SphereSpec("matte", (0.2, 0.3), 3.0), SphereSpec("glossy", (0.8, 0.7), 3.0)],
                             stand=True)
    with tempfile.TemporaryDirectory() as tmp:
        write_sphere_capture(sc, Path(tmp) / "spheres", truth=False)
        COMMANDS["calibrate"]({"spheres": [str(Path(tmp) / "spheres")]}, {}, Path(tmp) / "CAL")
        found = plt.imread(Path(tmp) / "CAL" / "spheres.png")
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.4))
    for ax, k, title in ((axes[0], 1, "lamp 2"), (axes[1], 5, "lamp 6")):
        img = sc.images[k].astype(float)
        ax.imshow(img, cmap="gray", vmin=np.percentile(img, 1), vmax=np.percentile(img, 99.5))
        ax.set_title(f"sphere capture, {title}")
    axes[2].imshow(found)
    axes[2].set_title("uvps calibrate: spheres.png")
    for ax in axes:
        ax.set_axis_off()
    fig.tight_layout()
    fig.savefig(out, dpi=80)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
