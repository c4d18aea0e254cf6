"""How frames travel: the DBC codec (``codec``), SecOC and the run's secret (``secoc``,
``auth``), python-can buses and the processes' bus options (``bus``), the bench's hub
(``hub``, WebSocket framing in ``wsframe``), bus logs in every format (``buslog``) and
SocketCAN vcan0 in User-mode Linux (``vcan`` with its C shim ``uml_xstate.c``)."""
