"""The bench's compiled kernels (numba, through ``firmware.kernels.njit``): ``plant``, ``sensors``."""
