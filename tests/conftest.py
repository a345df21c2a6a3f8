"""Test-session settings shared by every test file."""

import os

# The estimator works on many small matrices: OpenBLAS's thread pool only adds contention on
# small machines (5-10x slower on 2 busy cores). Must be set before numpy is imported.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
