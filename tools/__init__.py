"""Offline engineering tools: analysis, tuning, table generation."""

import calib  # noqa: F401  (first: pins OpenBLAS's kernels before numpy loads, calib.blas)
