"""One BLAS thread in the test process and the processes it starts; imported by
tests/conftest.py before anything loads numpy or scipy.

numpy and scipy each bundle an OpenBLAS that starts one thread per CPU and busy-waits between
calls. On this 2-core machine (two hyperthreads of one core, shared with other processes) the
waiting threads take the core from the one doing the work: ``feature_height``'s bounded
least-squares fit (an SVD of a tall Jacobian per step) took 10x the CPU time, and
tests/analysis/test_feature.py went from 680 s to 140 s wall (load 8) with this setting, with
bit-identical results. OpenBLAS reads the variable once, when the library loads, so it must be
set before numpy's first import; a value given in the environment is kept.
"""

from __future__ import annotations

import os
import sys
import warnings

#: the variable OpenBLAS reads at load time, and the thread count the suite runs with
ENV = "OPENBLAS_NUM_THREADS"
THREADS = "1"

if "numpy" in sys.modules:  # a plugin loaded it first: this process keeps its threads
    warnings.warn(f"numpy was loaded before tests/conftest.py: {ENV} is too late for the test "
                  "process (the processes it starts still get it)", stacklevel=1)
os.environ.setdefault(ENV, THREADS)
