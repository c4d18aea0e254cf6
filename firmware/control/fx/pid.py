"""The incremental PID in fixed point (C: ``pid_step``)."""

from __future__ import annotations

from firmware.fixedpoint import clamp, mul, sat32, sub
from firmware.fx.state import FxPid
from firmware.fx.tables import F_ACC, F_FORCE, F_JERK, F_VEL, FxTables, cm


def pid_step(T: FxTables, st: FxPid, e: int, kp: int, ki: int, kd: int) -> tuple:
    """Incremental PID (firmware.control.pid) with gains in the table's formats; returns
    (u, tp, ti, td) with the increments du/dK."""
    tp = sub(e, st.e1)
    ti = cm(T.dt, e, F_ACC, F_VEL)
    td = cm(T.inv_dt, sat32(e - 2 * st.e1 + st.e2), F_ACC, F_JERK)
    u = (cm(T.pid_leak, st.u, F_FORCE, F_FORCE) + mul(kp, tp, T.f_kp + F_ACC - F_FORCE)
         + mul(ki, ti, T.f_ki + F_VEL - F_FORCE) + mul(kd, td, T.f_kd + F_JERK - F_FORCE))
    lim = T.force_limit.m
    st.u = clamp(sat32(u), -lim, lim)
    st.e2, st.e1 = st.e1, e
    return st.u, tp, ti, td
