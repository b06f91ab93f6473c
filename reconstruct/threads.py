"""Thread pools sized by the program, not by the user's shell.

Training a small net calls BLAS on vectors of a few hundred numbers (scipy's L-BFGS-B steps):
OpenBLAS's default of one thread per core only adds hand-offs, and on a loaded machine each
hand-off can wait for a descheduled thread. Measured here, scipy 1.17, 150-parameter problem
under load: 25 ms per L-BFGS-B evaluation with 2 OpenBLAS threads, 0.04 ms with one. The
search of bench.speed in a plain shell, before and after training ran inside
`single_threaded` (two runs six minutes apart, scikit-learn's lbfgs 1.2 s in both): sphere
cap 35.0 s → 5.2 s, rough surface 12.3 s → 11.8 s; the gain depends on the load.

Only the training is limited, and landmark Isomap's small MDS (250 landmarks: its eigenvectors
and the product that places every point, so a 20,000-point embedding has the same bits
whatever the shell sets). Full Isomap's dense eigenproblems do use a second core. Capping
every pool of the scan engine's two worker processes at one thread each (threadpoolctl in the
pool's initializer) took bench.scan's vase from 53 s to 81 s on a quiet machine.
"""

from __future__ import annotations

import contextlib
import sys

from threadpoolctl import ThreadpoolController

#: The pools found, and how many modules were imported when they were looked for: a module
#: imported since may have loaded another (each look took 0.8-3.5 ms, three times a chart fit).
_found: tuple[int, ThreadpoolController] | None = None


@contextlib.contextmanager
def single_threaded():
    """BLAS and OpenMP pools at one thread inside the block (restored after)."""
    global _found
    if _found is None or _found[0] != len(sys.modules):
        _found = (len(sys.modules), ThreadpoolController())
    with _found[1].limit(limits=1):
        yield
