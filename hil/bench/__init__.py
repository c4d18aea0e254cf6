"""The bench as processes: one node per process (``procs``, ``python -m hil ecu|plant|app``)
and the supervisor that starts them, the hub and the log, and judges the run (``supervisor``,
``hil run``)."""
