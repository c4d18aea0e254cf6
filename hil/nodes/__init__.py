"""The bench's three CAN nodes as frame-driven state machines: no sockets, no clock.

``PlantNode`` (the simulator: road, quarter car, sensors, passive twin), ``EcuNode`` (the
firmware behind its receive/transmit path) and ``AppNode`` (the driver-app emulator) only
exchange ``(frame_id, payload)`` pairs encoded with the DBC. The same objects run in one
process (``hil sim``, :func:`run_in_process`) and as three processes on a CAN bus
(``hil run``, ``hil.bench.procs``), so the two harnesses compute the same thing by construction.

Lockstep protocol (deterministic, as fast as the bus allows), per tick k:
  1. the plant samples its sensors and sends, in this order, VEHICLE_SPEED, PLANT_SUPPLY and
     SIM_TRUTH (every 10 ms), ENERGY_STATUS (every 100 ms), PLANT_SENSORS (every tick);
  2. on PLANT_SENSORS the ECU steps once and sends ECU_STATUS and ECU_ESTIMATES (every 10 ms)
     and MODE_RECOMMEND (every 100 ms and on change);
  3. the app answers every MODE_RECOMMEND with exactly one DRIVER_REQUEST (a new request or
     the heartbeat repeating the last), which the ECU applies from tick k+1;
  4. the ECU sends ACTUATOR_CMD last: at once, or after that answer when it sent a
     MODE_RECOMMEND; the plant steps when the command is in.
Every frame is thus caused by the one before it, so the order on the bus is fixed and the
log of a lockstep run is the same bytes as ``hil sim``'s. Periods come from the DBC's
GenMsgCycleTime. In ``realtime`` pacing nobody waits: the ECU sends its command at once, the
plant steps on its 1 kHz clock with the latest valid command.
"""

from hil.nodes.app import POLICIES, QUEUED, REQ_KINDS, AppNode
from hil.nodes.base import (ID, MISSING, NAME_OF, OWNER, Frame, LockstepClock, Tx, message_name,
                            period_ticks, rx_spec)
from hil.nodes.ecu import ECU_TRACE, HASHED, EcuNode
from hil.nodes.inprocess import run_in_process, warm_up
from hil.nodes.plant import TRACE, PlantNode

__all__ = ["AppNode", "ECU_TRACE", "EcuNode", "Frame", "HASHED", "ID", "LockstepClock",
           "MISSING", "NAME_OF", "OWNER", "POLICIES", "PlantNode", "QUEUED", "REQ_KINDS",
           "TRACE", "Tx", "message_name", "period_ticks", "rx_spec", "run_in_process",
           "warm_up"]
