"""``python -m hil xcp measure``: one dynamic DAQ list on an event, for S seconds of the ECU's
time, to an MF4 file (asammdf) of physical values over the ECU's time. Each sample carries
the tick it was taken at (``in.tick``, added to the list: pyxcp hands the DTO timestamps
over relative to the first), so a lost sample is a gap in the ticks: reported, and the exit
status is 1."""

from __future__ import annotations

import logging
import sys
import time

import numpy as np

from calib.a2l import EVENTS
from hil.apps import xcptool as xt

STALL_FACTOR = 5          # no sample for this many --timeout: the bench stopped
TICK = "in.tick"


def _policy(lists):
    from pyxcp.daq_stim import DaqOnlinePolicy

    class Collect(DaqOnlinePolicy):
        def __init__(self):
            # (a logger given: pyxcp then reads no command line and no config file)
            super().__init__(lists, logger=logging.getLogger("hil.xcp.measure"))
            self.pid_off = False
            self.rows: list = []

        def initialize(self):
            pass

        def finalize(self):
            pass

        def on_daq_list(self, n, t0, t1, payload):
            self.rows.append((t1, list(payload)))

    return Collect()


def measure(args, key, a2l, bus, items, event: int) -> dict:
    from pyxcp.daq_stim import DaqList

    for it in items:
        if it.count != 1 or it.dtype not in xt.DAQ_TYPES:
            raise ValueError(f"{it.name}: DAQ on classic CAN carries 32-bit and 8-bit scalars "
                             "(pick an element NAME[i]; read doubles with get)")
    tick = a2l.item(TICK)
    chosen = [tick] + [it for it in items if it.name != TICK]
    lst = DaqList(name="hil", event_num=event, stim=False, enable_timestamps=True,
                  measurements=[(it.name, it.address, 0, xt.DAQ_TYPES[it.dtype])
                                for it in chosen], priority=0, prescaler=args.prescaler)
    pol = _policy([lst])
    step = EVENTS[event][3] * args.prescaler
    want = int(round(args.seconds * 1000 / step))          # samples in S s of ECU time
    stalled = False
    with xt.connected(bus, key, policy=pol, timeout=args.timeout) as x:
        xt.session(x, a2l)
        pol.setup()
        pol.start()
        last_n, last_t, shown = 0, time.monotonic(), 0.0
        while len(pol.rows) < want:
            time.sleep(0.05)
            now = time.monotonic()
            if len(pol.rows) != last_n:
                last_n, last_t = len(pol.rows), now
            elif now - last_t > STALL_FACTOR * args.timeout:
                stalled = True
                break
            if not args.json and now - shown >= 1.0:
                shown = now
                print(f"measure: {len(pol.rows)} / {want} samples", file=sys.stderr,
                      flush=True)
        pol.stop()
        x.disconnect()
    rows = pol.rows[:want]
    if not rows:
        raise RuntimeError("no DAQ sample came (is the bench running?)")
    heads = [h[0] for h in pol.daq_lists[0].headers]
    raw = {h: np.array([r[1][i] for r in rows]) for i, h in enumerate(heads)}
    ticks = raw[TICK].astype(np.int64)
    gaps = np.diff(ticks)
    lost = int(np.sum(gaps // step - 1)) if len(gaps) else 0
    if np.any(gaps <= 0) or np.any(gaps % step):
        raise RuntimeError(f"DAQ samples out of step (every {step} ticks expected)")
    _write_mf4(args.out, items, raw, ticks * 1e-3)
    return {"out": args.out, "event": args.event, "prescaler": args.prescaler,
            "samples": len(rows), "first_tick": int(ticks[0]), "last_tick": int(ticks[-1]),
            "lost": lost + (want - len(rows) if stalled else 0), "stalled": stalled}


def _write_mf4(path, items, raw: dict, t: np.ndarray) -> None:
    from asammdf import MDF, Signal

    mdf = MDF(version="4.10")
    sigs = []
    for it in items:
        values = raw[it.name].astype(float) * it.factor if it.factor != 1.0 \
            else raw[it.name]
        sigs.append(Signal(samples=values, timestamps=t, name=it.name, unit=it.unit,
                           comment="python -m hil xcp measure (ECU time)"))
    mdf.append(sigs, comment="XCP DAQ of the suspension ECU")
    mdf.save(path, overwrite=True)
    mdf.close()
