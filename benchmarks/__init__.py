"""ambhil's benchmarks: each module measures one thing and prints it in one format.

Run from the repository root, with the project's environment::

    .venv/bin/python -m benchmarks.NAME [--repeat N] [options]     # --help for the options

Every module prints a header (what, the commit, the machine and its load) and its figures as
median [min, max] over ``--repeat`` runs.  The list, with today's figures, is
benchmarks/README.md; what the figures mean for a user is docs/performance.md.

One BLAS thread: the small dense problems of this code are 10-50x slower with two threads on a
shared machine (docs/performance.md), so unless the caller sets them, the benchmarks set
``OPENBLAS_NUM_THREADS`` (and OMP/MKL) to 1 here, before numpy is imported, as ``./ambhil-dev``
does; the processes they start inherit it.
"""
import os as _os

for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    _os.environ.setdefault(_var, "1")
