"""Diagnostics as in a production ECU: model-based fault detection (``fdi``), the DTC memory
with ISO 14229 status bytes and snapshots (``dtc``), both compiled stages of the tick, and
the UDS service dispatch (``uds``: request bytes in, response bytes out, Python between
ticks, on the state record through ``view``). Pure code: time is the tick count."""

SESSION_DEFAULT, SESSION_EXTENDED = 0x01, 0x03
