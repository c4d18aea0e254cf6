"""The actuator stage in fixed point (``firmware.actuator``'s twin; C: ``current_reference``,
``actuator_step``, ``actuator_reset``): force -> current reference -> H-bridge voltage with the
EMF observer and the integral correction -> Q15 duty."""

from __future__ import annotations

from firmware.fixedpoint import add, clamp, rshift_round, same_sign_or_zero, sat16, sat32, sub
from firmware.fx.state import FxState
from firmware.fx.tables import F_ACC, F_CUR, F_FORCE, F_VEL, F_VOLT, FxTables, cm


def current_reference(T: FxTables, force: int, rel: int, compensate: bool) -> int:
    """C: ``current_reference``."""
    demand = add(force, cm(T.friction, rel, F_VEL, F_FORCE)) if compensate else force
    g = T.inv_eta_kf if same_sign_or_zero(demand, rel) else T.eta_over_kf
    lim = T.current_limit.m
    return clamp(cm(g, demand, F_FORCE, F_CUR), -lim, lim)


def step(T: FxTables, s: FxState, i_ref: int, rel: int, regen: bool, rel_acc: int) -> int:
    """C: ``actuator_step``."""
    i_meas = s.cur
    if s.observer_valid:
        emf = sub(s.voltage, cm(T.inv_cur_b, sub(i_meas, cm(T.cur_a, s.i_prev, F_CUR, F_CUR)),
                                F_CUR, F_VOLT))
        emf = add(emf, cm(T.kf_dt, rel_acc, F_ACC, F_VOLT))
    else:
        emf = cm(T.kf, add(rel, cm(T.half_dt, rel_acc, F_ACC, F_VEL)), F_VEL, F_VOLT)
    v_dc, per_v = (T.v_storage.m, T.duty_per_v_storage) if regen else (T.v_bus.m, T.duty_per_v_bus)
    v_ff = add(emf, cm(T.inv_cur_b, sub(i_ref, cm(T.cur_a, i_meas, F_CUR, F_CUR)), F_CUR, F_VOLT))
    v = add(v_ff, s.integ)
    lo, hi = -v_dc, v_dc
    if regen:
        r = cm(T.regen_min_ratio, emf, F_VOLT, F_VOLT)
        a, b = (r, emf) if r <= emf else (emf, r)
        lo, hi = max(lo, a), min(hi, b)
    saturated = v < lo or v > hi
    v = min(hi, max(lo, v))
    if not saturated:
        il = T.integ_limit.m
        s.integ = clamp(add(s.integ, cm(T.cur_ki, sub(s.i_ref_prev, i_meas), F_CUR, F_VOLT)), -il, il)
    s.i_ref_prev = i_ref
    duty = sat16(rshift_round(v * per_v.m, per_v.frac + F_VOLT))
    s.voltage = sat32(rshift_round(duty * v_dc, 15))
    s.i_prev = i_meas
    s.observer_valid = True
    return duty


def reset(s: FxState) -> None:
    """C: ``actuator_reset``."""
    s.integ = 0
    s.i_ref_prev = 0
    s.voltage = 0
    s.observer_valid = False
