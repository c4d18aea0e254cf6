"""The people's side of the bus: the driver's app logic (``driver``), its browser page
(``webapp``) and the diagnostic tester (``diag``, ``hil diag``)."""
