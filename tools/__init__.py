"""Offline engineering tools: analysis, tuning, table generation."""

import hil  # noqa: F401  (first: pins OpenBLAS's kernels before numpy loads, hil.blas)
