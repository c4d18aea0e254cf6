"""HIL/SIL side of the project: everything with I/O, the plant models and the CLIs."""

from hil import blas as _blas

_blas.pin()      # before numpy loads: the same bytes on every x86-64 host (hil.blas)
