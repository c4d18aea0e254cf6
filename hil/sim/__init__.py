"""The simulated world: ISO 8608 roads and routes (``road``), the quarter-car plant with its
motor, bridge and storage (``plant``), the sensors with noise and ADC quantisation
(``sensors``), ride metrics (``metrics``) and the open-loop drive of a route (``drive``). No bus,
no ECU: the nodes (``hil.nodes``) put these on one."""
