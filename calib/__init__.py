"""Calibration, the design-time layer between the firmware and the bench: everything that turns a
vehicle into the numbers the ECU runs with (``firmware.params.EcuParams``), offline and with
scipy allowed. Layers (import-linter contracts in ``pyproject.toml``): ``firmware`` <- ``calib``
<- ``hil`` <- ``tools``.

- ``options``: ``DesignOptions``, every design choice and named constant (TOML-overridable);
- ``ecu_params``: ``build(cfg, opts, gains_file)``, the ECU's calibration (AKF model, grade
  tables, modes, controllers, actuator), the gains files;
- ``model``: the linear quarter car and its exact (Lyapunov) statistics;
- ``linear``: LQR, the exact limits of control, the safety design; ``galqr``: the GA-LQR tuning;
- ``fx_tables``: the fixed-point path's constants; ``c_tables``: the C99 tables;
- ``iso8608``: road grades and the PSD convention; ``errors``: ``ConfigError``;
- ``blas``: pins OpenBLAS's kernels (the same bytes on every x86-64 host), run on import,
  before numpy loads; ``jitcache``: numba's cache directory, keyed by the compiled sources;
  ``cache``: the design cache (calibrations kept on disk).
"""

from calib import blas as _blas
from calib import jitcache as _jitcache

_blas.pin()      # before numpy loads (calib.blas)
_jitcache.pin()  # before numba loads: its cache keyed by the compiled sources (calib.jitcache)
