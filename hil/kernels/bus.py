"""The bench's messages as the compiled nodes see them (``hil.kernels.ecunode``,
``hil.kernels.silloop``): the messages by index (``M_*``: rows of ``hil.kernels.frames``'
``MSG`` table, in ``MESSAGES``' order), the signals they pack and unpack (``U_*``: rows of
``FIELD``, in ``USES``' order; ECU_STATUS's fault signals follow, one per bit of the fault
word), the ECU's and the plant's receivers (``R_*``) and the SecOC rows (``S_*``).
``hil.transport.codec.Codec.bus_tables`` lays the tables out from the DBC.
"""

from __future__ import annotations

MESSAGES = ("VEHICLE_SPEED", "PLANT_SUPPLY", "SIM_TRUTH", "ENERGY_STATUS", "PLANT_SENSORS",
            "ACTUATOR_CMD", "ECU_STATUS", "ECU_ESTIMATES", "MODE_RECOMMEND", "DRIVER_REQUEST")
(M_SPEED, M_SUPPLY, M_TRUTH, M_ENERGY, M_SENSORS, M_CMD, M_STATUS, M_EST, M_REC,
 M_REQ) = range(len(MESSAGES))
USES = (("VEHICLE_SPEED", "SPEED"), ("PLANT_SUPPLY", "SUPPLY_VOLTAGE_RAW"),
        ("SIM_TRUTH", "TRUE_ROAD"), ("SIM_TRUTH", "TRUE_DTD"), ("SIM_TRUTH", "TRUE_SWS"),
        ("SIM_TRUTH", "TRUE_GRADE"), ("SIM_TRUTH", "SEGMENT"),
        ("ENERGY_STATUS", "STORED_ENERGY"), ("ENERGY_STATUS", "SUPPLY_ENERGY"),
        ("PLANT_SENSORS", "BODY_ACCEL_RAW"), ("PLANT_SENSORS", "WHEEL_ACCEL_RAW"),
        ("PLANT_SENSORS", "SUSP_DEFL_RAW"), ("PLANT_SENSORS", "MOTOR_CURRENT_RAW"),
        ("ACTUATOR_CMD", "DUTY"), ("ACTUATOR_CMD", "REGEN"), ("ACTUATOR_CMD", "ENABLE"),
        ("ACTUATOR_CMD", "SENSOR_SEQ"),
        ("ECU_STATUS", "ACTIVE_MODE"), ("ECU_STATUS", "ESTIMATED_GRADE"),
        ("ECU_STATUS", "REASON"), ("ECU_STATUS", "BA_RMS"), ("ECU_STATUS", "DTD_RMS"),
        ("ECU_ESTIMATES", "ROAD_EST"), ("ECU_ESTIMATES", "DTD_EST"),
        ("ECU_ESTIMATES", "GQ_LOG"), ("ECU_ESTIMATES", "FORCE_CMD"),
        ("MODE_RECOMMEND", "RECOMMENDED_MODE"), ("MODE_RECOMMEND", "ESTIMATED_GRADE"),
        ("MODE_RECOMMEND", "ACTIVE_MODE"), ("MODE_RECOMMEND", "REASON"),
        ("MODE_RECOMMEND", "OVERRIDE"),
        ("DRIVER_REQUEST", "REQ_KIND"), ("DRIVER_REQUEST", "REQ_MODE"),
        ("DRIVER_REQUEST", "REQ_ID"), ("ECU_STATUS", "DEGRADED"))
(U_SPEED, U_SUPPLY, U_TRUE_ROAD, U_TRUE_DTD, U_TRUE_SWS, U_TRUE_GRADE, U_SEGMENT, U_STORED,
 U_DRAWN, U_SENS, _, _, _, U_DUTY, U_REGEN, U_ENABLE, U_SEQ, U_ST_ACTIVE, U_ST_GRADE,
 U_ST_REASON, U_ST_BA, U_ST_DTD, U_ROAD_EST, U_DTD_EST, U_GQ, U_FORCE, U_REC, U_REC_GRADE,
 U_REC_ACTIVE, U_REC_REASON, U_REC_OVERRIDE, U_KIND, U_MODE, U_ID, U_ST_DEGRADED) = range(len(USES))
# then ECU_STATUS's fault signals, one per bit of the fault word (``FAULT_BITS`` gives the bits)
U_FAULTS = len(USES)

R_SPEED, R_SUPPLY, R_SENSORS, R_REQ, R_CMD = range(5)    # the ECU's four receivers, the plant's
S_CMD_TX, S_CMD_RX, S_REQ_TX, S_REQ_RX = range(4)        # SecOC: ECU -> plant, app -> ECU
NMSG = len(MESSAGES)
