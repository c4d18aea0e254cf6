"""Imported before any test module: ``hil`` pins OpenBLAS's kernels before numpy loads."""

import hil  # noqa: F401
