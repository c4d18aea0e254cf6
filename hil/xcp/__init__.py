"""XCP on CAN: the ECU node's calibration and measurement slave (``docs/xcp.md``).

Written by hand: no maintained Python XCP slave exists (pyxcp, the master, tests it).
``protocol``: the codes and errors; ``memory``: the image over the live records and the
calibration's staging; ``daq``: dynamic DAQ lists and their sampling; ``slave``: the
command processor.
"""
