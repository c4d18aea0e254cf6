"""HIL/SIL side of the project: everything with I/O, the plant models and the CLIs."""

import calib  # noqa: F401  (first: pins OpenBLAS's kernels before numpy loads, calib.blas)
