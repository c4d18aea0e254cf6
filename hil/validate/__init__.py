"""Validation over many runs: the fault campaign (``faults``, ``hil faults``), campaigns over
routes, cars and seeds on Dask (``campaign``), the false-alarm campaign (``alarms``) and the
SIL acceptance every run is judged by (``acceptance``)."""
