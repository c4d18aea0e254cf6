"""The UDS server (ISO 14229-1) as a pure function: one request's bytes in, the response's
bytes out (None: no response, as with suppressPosRspMsgIndicationBit). The ISO-TP transport
around it is the node's (``hil.apps.diag``).

Services: 0x10 DiagnosticSessionControl (01 default, 03 extended; S3 5 s), 0x3E TesterPresent,
0x22 ReadDataByIdentifier (``DIDS``), 0x19 ReadDTCInformation (01, 02, 04, 06, 0A), 0x14
ClearDiagnosticInformation, 0x11 ECUReset (01, 03; extended session), 0x85 ControlDTCSetting
(01 on, 02 off; extended session). Anything else gets the negative response ISO 14229-1
prescribes: 7F SID NRC.
"""

from __future__ import annotations

from firmware.diag import SESSION_DEFAULT, SESSION_EXTENDED, dtc
from firmware.diag.view import DiagView

NRC_SERVICE_NOT_SUPPORTED = 0x11
NRC_SUBFUNCTION_NOT_SUPPORTED = 0x12
NRC_INCORRECT_LENGTH = 0x13
NRC_CONDITIONS_NOT_CORRECT = 0x22
NRC_REQUEST_OUT_OF_RANGE = 0x31
NRC_SERVICE_NOT_IN_SESSION = 0x7F
SPRMIB = 0x80                       # suppressPosRspMsgIndicationBit
P2_MS, P2_STAR_10MS = 50, 500       # the session timing the ECU announces
S3_MS = 5000                        # non-default session timeout without a request
MAX_DIDS_PER_REQUEST = 8

# the data identifiers of 0x22 (and the snapshot record's), with their lengths
DID_SOFTWARE_VERSION = 0xF195
DID_CALIBRATION_SHA256 = 0xF1A0
DID_VEHICLE_SHA256 = 0xF1A1
DID_ACTIVE_MODE = 0x0100
DID_GRADE = 0x0101
DID_SUPPLY_VOLTAGE = 0x0102
DID_FAULT_WORD = 0x0103
DID_BA_RMS = 0x0104
DID_DTD_RMS = 0x0105
DID_TICK = 0x0106
DID_DEGRADED = 0x0107                # degraded operation (firmware.diag.degrade): state (0 normal,
#                                      1 a sensor out, 2 fail-safe latched, 3 a sensor out to the
#                                      end of the cycle), the sensor out (0xFF
#                                      none; 0 BA, 1 WA, 2 SWS, 3 current), the tick it went out
#                                      and the second fault's (0xFFFFFFFF: none)
DID_SNAPSHOT = 0x0200               # snapshot record 1: tick, speed, grade, mode, BA, DTD, supply
SNAPSHOT_RECORD = 0x01
SNAPSHOT_SIZE = 14
EXT_RECORDS = (0x01, 0x02, 0x03)    # occurrence counter, FDC (signed), aging counter
DIDS = (DID_SOFTWARE_VERSION, DID_CALIBRATION_SHA256, DID_VEHICLE_SHA256, DID_ACTIVE_MODE,
        DID_GRADE, DID_SUPPLY_VOLTAGE, DID_FAULT_WORD, DID_BA_RMS, DID_DTD_RMS, DID_TICK,
        DID_DEGRADED)
SOFTWARE_VERSION_LEN = 16


def negative(sid: int, nrc: int) -> bytes:
    return bytes((0x7F, sid, nrc))


def handle(ds: DiagView, params, tick: int, req: bytes) -> bytes | None:
    """One request -> its response. ``params``: the EcuParams (identification DIDs)."""
    if not req:
        return None
    expire(ds, tick, params.dt_s)
    if ds.session != SESSION_DEFAULT:
        ds.session_tick = tick
    sid = req[0]
    fn = _SERVICES.get(sid)
    if fn is None:
        return negative(sid, NRC_SERVICE_NOT_SUPPORTED)
    return fn(ds, params, tick, req)


def expire(ds: DiagView, tick: int, dt_s: float) -> None:
    """S3: a non-default session ends after ``S3_MS`` without a request."""
    if ds.session != SESSION_DEFAULT and (tick - ds.session_tick) * dt_s * 1000 > S3_MS:
        ds.session = SESSION_DEFAULT
        dtc_setting_on(ds)


def dtc_setting_on(ds: DiagView) -> None:
    ds.dtc.setting_on = True


def _sub(req: bytes) -> tuple[int, bool]:
    return req[1] & 0x7F, bool(req[1] & SPRMIB)


def _session(ds, params, tick, req):
    if len(req) != 2:
        return negative(0x10, NRC_INCORRECT_LENGTH)
    sub, quiet = _sub(req)
    if sub not in (SESSION_DEFAULT, SESSION_EXTENDED):
        return negative(0x10, NRC_SUBFUNCTION_NOT_SUPPORTED)
    if sub == SESSION_DEFAULT:
        dtc_setting_on(ds)            # leaving the extended session ends its settings
    ds.session, ds.session_tick = sub, tick
    if quiet:
        return None
    return bytes((0x50, sub)) + P2_MS.to_bytes(2, "big") + P2_STAR_10MS.to_bytes(2, "big")


def _tester_present(ds, params, tick, req):
    if len(req) != 2:
        return negative(0x3E, NRC_INCORRECT_LENGTH)
    sub, quiet = _sub(req)
    if sub != 0:
        return negative(0x3E, NRC_SUBFUNCTION_NOT_SUPPORTED)
    return None if quiet else bytes((0x7E, 0x00))


def _reset(ds, params, tick, req):
    if len(req) != 2:
        return negative(0x11, NRC_INCORRECT_LENGTH)
    sub, quiet = _sub(req)
    if sub not in (0x01, 0x03):
        return negative(0x11, NRC_SUBFUNCTION_NOT_SUPPORTED)
    if ds.session != SESSION_EXTENDED:
        return negative(0x11, NRC_SERVICE_NOT_IN_SESSION)
    ds.reset_requested = sub
    return None if quiet else bytes((0x51, sub))


def _control_dtc_setting(ds, params, tick, req):
    if len(req) < 2:
        return negative(0x85, NRC_INCORRECT_LENGTH)
    sub, quiet = _sub(req)
    if sub not in (0x01, 0x02):
        return negative(0x85, NRC_SUBFUNCTION_NOT_SUPPORTED)
    if len(req) != 2:                 # (no DTCSettingControlOptionRecord supported)
        return negative(0x85, NRC_REQUEST_OUT_OF_RANGE)
    if ds.session != SESSION_EXTENDED:
        return negative(0x85, NRC_SERVICE_NOT_IN_SESSION)
    ds.dtc.setting_on = sub == 0x01
    return None if quiet else bytes((0xC5, sub))


def _clear(ds, params, tick, req):
    if len(req) != 4:
        return negative(0x14, NRC_INCORRECT_LENGTH)
    if not ds.clear(int.from_bytes(req[1:4], "big")):
        return negative(0x14, NRC_REQUEST_OUT_OF_RANGE)
    return bytes((0x54,))


def did_data(ds: DiagView, params, did: int) -> bytes | None:
    mode, grade, faults, _, ba, dtd, t, supply = ds.view
    if did == DID_SOFTWARE_VERSION:
        return params.software_version.encode("ascii")[:SOFTWARE_VERSION_LEN].ljust(
            SOFTWARE_VERSION_LEN, b"\x00")
    if did == DID_CALIBRATION_SHA256:
        return bytes(params.calibration_sha256)
    if did == DID_VEHICLE_SHA256:
        return bytes(params.vehicle_sha256)
    if did == DID_ACTIVE_MODE:
        return bytes((mode,))
    if did == DID_GRADE:
        return bytes((grade,))
    if did == DID_SUPPLY_VOLTAGE:
        return supply.to_bytes(2, "big")
    if did == DID_FAULT_WORD:
        return (faults & 0xFFFFFFFF).to_bytes(4, "big")
    if did == DID_BA_RMS:
        return min(ba, 0xFFFF).to_bytes(2, "big")
    if did == DID_DTD_RMS:
        return min(dtd, 0xFFFF).to_bytes(2, "big")
    if did == DID_TICK:
        return (max(t, 0) & 0xFFFFFFFF).to_bytes(4, "big")
    if did == DID_DEGRADED:
        state, sensor, since, second = ds.degraded
        return (bytes((state, sensor & 0xFF)) + (since & 0xFFFFFFFF).to_bytes(4, "big")
                + (second & 0xFFFFFFFF).to_bytes(4, "big"))
    return None


def _read_did(ds, params, tick, req):
    n = len(req) - 1
    if n < 2 or n % 2 or n // 2 > MAX_DIDS_PER_REQUEST:
        return negative(0x22, NRC_INCORRECT_LENGTH)
    out = bytearray((0x62,))
    for k in range(1, len(req), 2):
        did = int.from_bytes(req[k:k + 2], "big")
        data = did_data(ds, params, did)
        if data is None:
            return negative(0x22, NRC_REQUEST_OUT_OF_RANGE)
        out += req[k:k + 2] + data
    return bytes(out)


def snapshot_bytes(s: dtc.Snapshot) -> bytes:
    return (s.tick.to_bytes(4, "big") + s.speed_cmps.to_bytes(2, "big")
            + bytes((s.grade, s.mode)) + min(s.ba_rms_mmps2, 0xFFFF).to_bytes(2, "big")
            + min(s.dtd_rms_um, 0xFFFF).to_bytes(2, "big") + s.supply_mv.to_bytes(2, "big"))


def _dtc_record(ds: DiagView, i: int) -> bytes:
    return dtc.DTCS[i].code.to_bytes(3, "big") + bytes((dtc.status_of(ds.dtc, i),))


def _read_dtc(ds, params, tick, req):
    if len(req) < 2:
        return negative(0x19, NRC_INCORRECT_LENGTH)
    sub = req[1] & 0x7F               # (no suppressed response for 0x19)
    mem = ds.dtc
    if sub in (0x01, 0x02):
        if len(req) != 3:
            return negative(0x19, NRC_INCORRECT_LENGTH)
        mask = req[2] & dtc.AVAILABILITY_MASK
        hits = [i for i in range(len(dtc.DTCS)) if dtc.status_of(mem, i) & mask]
        if sub == 0x01:               # format 0x01: ISO 14229-1 DTC format
            return bytes((0x59, 0x01, dtc.AVAILABILITY_MASK, 0x01)) + len(hits).to_bytes(2, "big")
        return bytes((0x59, 0x02, dtc.AVAILABILITY_MASK)) + b"".join(
            _dtc_record(ds, i) for i in hits)
    if sub == 0x0A:
        if len(req) != 2:
            return negative(0x19, NRC_INCORRECT_LENGTH)
        return bytes((0x59, 0x0A, dtc.AVAILABILITY_MASK)) + b"".join(
            _dtc_record(ds, i) for i in range(len(dtc.DTCS)))
    if sub in (0x04, 0x06):
        if len(req) != 6:
            return negative(0x19, NRC_INCORRECT_LENGTH)
        i = dtc.BY_CODE.get(int.from_bytes(req[2:5], "big"))
        rec = req[5]
        if i is None:
            return negative(0x19, NRC_REQUEST_OUT_OF_RANGE)
        e = mem.entries[i]
        out = bytearray((0x59, sub)) + _dtc_record(ds, i)
        if sub == 0x04:
            if rec not in (SNAPSHOT_RECORD, 0xFF):
                return negative(0x19, NRC_REQUEST_OUT_OF_RANGE)
            if e.snapshot is not None:
                out += bytes((SNAPSHOT_RECORD, 1)) + DID_SNAPSHOT.to_bytes(2, "big") + \
                    snapshot_bytes(e.snapshot)
            return bytes(out)
        if rec not in EXT_RECORDS and rec != 0xFF:
            return negative(0x19, NRC_REQUEST_OUT_OF_RANGE)
        values = {0x01: e.occurrences, 0x02: e.fdc & 0xFF, 0x03: e.aging}
        for r in (EXT_RECORDS if rec == 0xFF else (rec,)):
            out += bytes((r, values[r]))
        return bytes(out)
    return negative(0x19, NRC_SUBFUNCTION_NOT_SUPPORTED)


_SERVICES = {0x10: _session, 0x3E: _tester_present, 0x11: _reset, 0x85: _control_dtc_setting,
             0x14: _clear, 0x22: _read_did, 0x19: _read_dtc}
