"""The ``uvps`` command's entry point: one BLAS thread unless the user chose otherwise.

uvps runs its own threads (the normals kernel's bands, the run folder's writers, Dask workers), and
OpenBLAS's threads on top of them made the additive term of a 10000 x 8000 capture take 72 s where
one thread takes 9.4 s on 2 cores (docs/decisions/speed.md, ``scripts/benchmark_speed.py --shape 8000 10000``).
BLAS reads its thread count when numpy is first imported, so it is set here, before anything
imports numpy; a value already in the environment is kept. Library users (``import uvps``) are not affected.
"""
import os
import sys

#: Commands whose process (``uvps`` or ``python -m uvps``, not a caller of :func:`main`) ends right after
#: its ``atexit`` handlers, without the interpreter's teardown (:func:`uvps.workers.exit_at_teardown`): ``batch``'s
#: process holds Dask, distributed, zarr and matplotlib, whose teardown took ~1 s once the batch was done.
EXIT_WITHOUT_TEARDOWN = ("batch",)
#: Environment variables set to "1" when absent.
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")


def main(argv=None):
    for name in BLAS_THREAD_VARIABLES:
        os.environ.setdefault(name, "1")
    from .cli import main as cli_main

    code = cli_main(argv)
    if argv is None and next((w for w in sys.argv[1:] if not w.startswith("-")), None) in EXIT_WITHOUT_TEARDOWN:
        from .workers import exit_at_teardown
        exit_at_teardown(code)
    return code
