"""Unit tests of the firmware's compiled stages (called from Python on the state record's
sub-records): ADC plausibility, the mode state machine, the actuator stage, PID and BP-PID."""

import dataclasses

import numpy as np
import pytest

from calib.ecu_params import build
from firmware import actuator, adc, control, modes, safety
from firmware import params as fp
from firmware.ecu import Ecu, Inputs, _counts, _request_faults
from firmware.ecu import init as ecu_init
from firmware.layout import params_record
from hil.config import default_vehicle

P = build(default_vehicle())


def records(p=P):
    """The calibration's record and a new ECU state record, as elements (np.void: numba
    takes them by reference, so a stage writes its state through)."""
    rec = params_record(p)
    return rec[0], ecu_init(p, rec)[0]


# -- ADC ---------------------------------------------------------------------------------------

def raw(**over):
    """Mid-scale counts of every channel in adc.CHANNELS order, some overridden by name."""
    mid = {name: getattr(P.adc, name).full_scale // 2 for name in adc.CHANNELS}
    mid.update(over)
    return tuple(mid[name] for name in adc.CHANNELS)


def sample(S, counts, explained=0):
    """adc.sample on the state's ADC (the inputs as the ECU takes them: ``firmware.ecu._counts``)
    with the SI values by channel name."""
    c = np.array([_counts(v) for v in counts], dtype=np.int64)
    faults = adc.sample(PR["adc"], S["adc"], c, explained)
    return dict(zip(adc.CHANNELS, S["adc"]["value"].tolist())), faults


PR, _ = records()


def test_adc_conversion_and_plausibility():
    _, S = records()
    v, faults = sample(S, raw())
    assert faults == 0
    ch = P.adc.body_accel
    assert v["body_accel"] == pytest.approx(ch.range_min + (ch.full_scale // 2) * ch.lsb)
    for bad in (-1, ch.full_scale + 1, float("nan"), 12.5, True):
        _, S = records()
        sample(S, raw())
        v, faults = sample(S, raw(body_accel=bad))
        assert faults == adc.FAULT_BIT["body_accel"], bad
        assert v["body_accel"] == pytest.approx(ch.range_min + (ch.full_scale // 2) * ch.lsb)  # held


def test_adc_no_sample_is_not_a_channel_fault():
    """A tick without a sample (a lost or late frame: None) holds the value and is not
    measured, but names no circuit fault (the frame checks name it) and leaves the fault
    state and its recovery count as they were."""
    _, S = records()
    v0, _ = sample(S, raw(body_accel=100))
    v, faults = sample(S, raw(body_accel=None, susp_defl=None))
    assert faults == 0 and v["body_accel"] == v0["body_accel"]
    assert not adc.measured(S["adc"], adc.BA) and adc.held(S["adc"], adc.BA)
    assert adc.measured(S["adc"], adc.WA) and adc.unsettled(PR["adc"], S["adc"])
    assert adc.good_count(S["adc"], adc.BA) == -1
    sample(S, raw(body_accel=-5))                     # a fault, then no sample: still one
    _, faults = sample(S, raw(body_accel=None))
    assert faults == adc.FAULT_BIT["body_accel"]
    for k in range(P.adc.recover_ticks):              # recovery counts good samples only
        _, faults = sample(S, raw())
        if k == P.adc.recover_ticks // 2:
            _, f2 = sample(S, raw(body_accel=None))
            assert f2 == adc.FAULT_BIT["body_accel"]
    assert faults == 0
    # the fail-safe hysteresis after a tick without a sample: recover_ticks samples
    sample(S, raw(speed=None))
    for k in range(P.adc.recover_ticks):
        assert adc.unsettled(PR["adc"], S["adc"])
        sample(S, raw())
    assert not adc.unsettled(PR["adc"], S["adc"])


def test_adc_stuck_at_rail_and_recovery_hysteresis():
    _, S = records()
    faults = 0
    for k in range(P.adc.rail_ticks):
        _, faults = sample(S, raw(wheel_accel=P.adc.wheel_accel.full_scale))
        assert bool(faults) == (k + 1 >= P.adc.rail_ticks)
    for k in range(P.adc.recover_ticks):
        _, faults = sample(S, raw())
        assert bool(faults) == (k + 1 < P.adc.recover_ticks)
    # speed at 0 counts is a car standing still, not a fault
    _, S = records()
    for _ in range(3 * P.adc.rail_ticks):
        _, faults = sample(S, raw(speed=0))
    assert faults == 0


def test_adc_explained_rail_is_clipped_not_faulty():
    """A rail the ECU explains is a sample beyond the range (not measured), not a fault; the
    same rail is a fault rail_ticks samples after the explanation ends."""
    _, S = records()
    bit, cur = adc.FAULT_BIT["motor_current"], adc.CHANNELS.index("motor_current")
    top = raw(motor_current=P.adc.motor_current.full_scale)
    for _ in range(5 * P.adc.rail_ticks):
        _, faults = sample(S, top, explained=bit)
        assert faults == 0 and not adc.measured(S["adc"], cur)
    # another channel's explanation does not cover it
    for k in range(P.adc.rail_ticks):
        _, faults = sample(S, top, explained=adc.FAULT_BIT["susp_defl"])
        assert faults == (bit if k + 1 >= P.adc.rail_ticks else 0)
    _, S = records()
    sample(S, raw())
    assert adc.measured(S["adc"], cur)


def test_ecu_explains_a_current_rail_by_the_estimated_velocity():
    """The ECU takes the motor current at its rail for a measurement beyond the range while its
    estimate's relative velocity is one at which the back-EMF alone drives the current there,
    and for a fault (stuck sensor) when the suspension moves slowly."""
    vehicle = default_vehicle()
    ap, cur = vehicle.actuator, vehicle.sensors.motor_current
    # the velocity at which K v - V = R I_rail, from the vehicle file's numbers
    v_emf = (min(ap.bus_voltage_v, ap.storage_voltage_v)
             + ap.winding_resistance_ohm * min(-cur.range_min, cur.range_max)) \
        / ap.force_constant_n_per_a
    assert P.adc.current_rail_mps < v_emf < 1.5 * P.adc.current_rail_mps
    bit = adc.FAULT_BIT["motor_current"]
    rail = P.adc.motor_current.full_scale
    for v_rel, expect_fault in ((1.1 * v_emf, False), (0.5 * P.adc.current_rail_mps, True)):
        e = Ecu(P)
        worst = 0
        for k in range(5 * P.adc.rail_ticks):
            e.x[0], e.x[1] = v_rel, 0.0       # the estimate the ECU starts the tick with
            worst |= e.step(Inputs(k, 2048, 2048, 2048, rail, 2000)).faults
        assert bool(worst & bit) == expect_fault, v_rel


# -- modes -------------------------------------------------------------------------------------

# these tests send a request every step; the spam limit has its own test below
MP = dataclasses.replace(P.modes, request_min_ticks=0)


class ModeState:
    """The mode stage's calibration and state records; the state's fields as attributes."""

    def __init__(self, mp):
        rec, state = records(dataclasses.replace(P, modes=mp))
        self._p, self._s = rec["modes"], state["modes"]

    def step(self, grade, kind, mode, counter, dtd=0.0, fault=False, kept=0x1F):
        return modes.step(self._p, self._s, grade, kind, mode, counter, dtd, fault, kept)

    def __getattr__(self, name):
        return int(self._s[name])


def run_modes(events, st=None, dtd=0.0, fault=False):
    st = st or ModeState(MP)
    out = []
    for grade, kind, mode, counter in events:
        out.append(st.step(grade, kind, mode, counter, dtd, fault))
    return st, out


def test_recommend_but_switch_only_on_acceptance():
    st, out = run_modes([(1, 0, 0, 0)] * 5)
    assert st.recommended == fp.MODE_COMFORT and out[-1] == MP.initial_mode
    st, out = run_modes([(1, fp.REQ_ACCEPT, fp.MODE_COMFORT, 1)], st)
    assert out[-1] == fp.MODE_COMFORT and st.events & modes.EVT_ACCEPTED
    # a repeated request (same counter) is not acted on again
    st, out = run_modes([(3, fp.REQ_ACCEPT, fp.MODE_COMPREHENSIVE, 1)], st)
    assert out[-1] == fp.MODE_COMFORT
    # accepting a mode that is no longer recommended: the recommendation changed while the
    # request was on its way (a race, not invalid data: no fault, U0405-81 stays unset)
    st, out = run_modes([(3, fp.REQ_ACCEPT, fp.MODE_SAFETY, 2)], st)
    assert out[-1] == fp.MODE_COMFORT and st.events == modes.EVT_STALE_ACCEPT
    assert _request_faults(st.events) == 0
    # ... and an ACCEPT of a mode that does not exist is invalid data
    st, out = run_modes([(3, 0, 0, 2)] * MP.request_min_ticks + [(3, fp.REQ_ACCEPT, 9, 3)], st)
    assert out[-1] == fp.MODE_COMFORT and st.events == modes.EVT_INVALID_REQUEST
    assert _request_faults(st.events) == safety.FAULT_INVALID_REQUEST


def test_refuse_and_choose():
    st, out = run_modes([(0, fp.REQ_REFUSE, 0, 1)])
    assert out[-1] == MP.initial_mode and st.events & modes.EVT_REFUSED
    st, out = run_modes([(0, fp.REQ_CHOOSE, fp.MODE_SAFETY, 2)], st)
    assert out[-1] == fp.MODE_SAFETY and st.recommended == fp.MODE_ENERGY
    for bad in (7, -1, 255):
        st, out = run_modes([(0, fp.REQ_CHOOSE, bad, 3 + bad % 5)], st)
        assert out[-1] == fp.MODE_SAFETY and st.events & modes.EVT_INVALID_REQUEST
    st, out = run_modes([(0, 9, 0, 12)], st)
    assert st.events & modes.EVT_INVALID_REQUEST


def test_request_spam_is_ignored_and_reported():
    mp = P.modes
    assert mp.request_min_ticks > 1
    st = ModeState(mp)
    step = lambda kind, mode, counter: st.step(1, kind, mode, counter)
    assert step(fp.REQ_CHOOSE, fp.MODE_SAFETY, 1) == fp.MODE_SAFETY
    # a new request every tick, alternating modes: none is acted on, each is reported
    for i in range(2, mp.request_min_ticks // 2):
        mode = fp.MODE_COMFORT if i % 2 else fp.MODE_ENERGY
        assert step(fp.REQ_CHOOSE, mode, i) == fp.MODE_SAFETY
        assert st.events & modes.EVT_REQUEST_RATE
    last = mp.request_min_ticks // 2 - 1
    # the spam keeps the window open: quiet for less than the limit is still too soon
    for _ in range(mp.request_min_ticks - 2):
        step(fp.REQ_CHOOSE, fp.MODE_COMFORT, last)          # heartbeat: same counter
    assert step(fp.REQ_CHOOSE, fp.MODE_COMFORT, last + 1) == fp.MODE_SAFETY
    assert st.events & modes.EVT_REQUEST_RATE
    # after a quiet interval a request is acted on
    for _ in range(mp.request_min_ticks):
        step(fp.REQ_CHOOSE, fp.MODE_COMFORT, last + 1)
    assert step(fp.REQ_CHOOSE, fp.MODE_COMFORT, last + 2) == fp.MODE_COMFORT
    assert st.events == modes.EVT_CHOSEN


def test_safety_override_first_then_back_to_driver_mode():
    st, _ = run_modes([(0, fp.REQ_CHOOSE, fp.MODE_ENERGY, 1)])
    limit = MP.safety_dtd_rms_limit
    st, out = run_modes([(0, 0, 0, 1)], st, dtd=1.01 * limit)
    assert out[-1] == fp.MODE_SAFETY and st.reason == modes.REASON_ROAD_HOLDING
    # below the exit level but inside the hold time: stays
    st, out = run_modes([(0, 0, 0, 1)] * (MP.safety_hold_ticks - 2), st, dtd=0.5 * limit)
    assert out[-1] == fp.MODE_SAFETY
    # the driver cannot leave safety while the override holds
    st, out = run_modes([(0, fp.REQ_CHOOSE, fp.MODE_COMFORT, 2)], st, dtd=0.5 * limit)
    assert out[-1] == fp.MODE_SAFETY
    st, out = run_modes([(0, 0, 0, 2)] * 3, st, dtd=0.5 * limit)
    assert out[-1] == fp.MODE_COMFORT and st.reason == modes.REASON_NONE   # the driver's choice


def test_fault_forces_failsafe():
    st, _ = run_modes([(1, fp.REQ_CHOOSE, fp.MODE_COMFORT, 1)])
    st, out = run_modes([(1, 0, 0, 1)], st, fault=True)
    assert out[-1] == fp.MODE_PASSIVE and st.reason == modes.REASON_FAULT


def test_ecu_opens_the_bridge_on_a_sensor_fault_within_the_tick():
    e = Ecu(P)
    ba, wa, defl, cur, _ = raw()
    inp = Inputs(0, ba, wa, defl, cur, 2000, fp.REQ_CHOOSE, fp.MODE_SAFETY, 1)
    for k in range(400):
        out = e.step(inp._replace(tick=k))
    assert out.enable and out.active_mode == fp.MODE_SAFETY
    out = e.step(inp._replace(tick=400, susp_defl=-5))
    assert not out.enable and out.duty_q15 == 0 and out.faults & adc.FAULT_BIT["susp_defl"]
    assert out.reason == modes.REASON_FAULT


# -- actuator ----------------------------------------------------------------------------------

def test_duty_rounding_and_saturation():
    assert actuator.duty_to_q15(0.5) == 16384
    assert actuator.duty_to_q15(-0.5) == -16384
    assert actuator.duty_to_q15(1.0) == 32767 and actuator.duty_to_q15(-1.0) == -32768
    assert actuator.duty_to_q15(7.0) == 32767 and actuator.duty_to_q15(-7.0) == -32768
    assert actuator.duty_to_q15(1.5 / 32768) == 2 and actuator.duty_to_q15(-1.5 / 32768) == -2


def test_current_reference_limits_and_efficiency():
    pl = P.plant
    big = actuator.current_reference(PR["plant"], PR["actuator"], 1e6, 0.1, True)
    assert big == pytest.approx(P.actuator.current_limit)
    assert P.actuator.current_limit == pytest.approx(0.95 * pl.current_limit)   # (the margin)
    # motoring needs more current than the ideal, generating less
    drive = actuator.current_reference(PR["plant"], PR["actuator"], 300.0, 0.1, False)
    brake = actuator.current_reference(PR["plant"], PR["actuator"], -300.0, 0.1, False)
    assert drive == pytest.approx(300.0 / (pl.efficiency * pl.force_constant))
    assert brake == pytest.approx(-300.0 * pl.efficiency / pl.force_constant)


def test_regen_voltage_keeps_power_flowing_into_storage():
    pl = P.plant
    for rel_vel in (0.3, -0.3):
        for i_ref in (-50.0, -5.0, 0.0, 5.0, 50.0):
            _, S = records()
            st = S["ctl"]["actuator"]
            i_meas = 0.0
            for _ in range(20):   # closed loop on a simple winding model
                actuator.step(PR["actuator"], PR["plant"], st, i_ref, i_meas, rel_vel, True,
                              0.5, 0.0, P.dt_s)
                emf = pl.force_constant * rel_vel
                lo, hi = sorted((0.5 * st["emf"], st["emf"]))
                assert lo - 2e-3 <= st["voltage"] <= hi + 2e-3     # quantised duty
                i_meas = (P.actuator.current_a * i_meas
                          + P.actuator.current_b * (st["voltage"] - emf))
                assert st["voltage"] * i_meas <= 1e-9              # power into the storage


# -- PID / BP-PID ------------------------------------------------------------------------------

def test_incremental_pid_equals_positional_without_leak():
    rng = np.random.default_rng(0)
    e = rng.normal(0, 1, 500)
    st = records()[1]["ctl"]["pid"]
    kp, ki, kd, dt = 3.0, 40.0, 0.01, 0.001
    for k in range(500):
        u = control.pid_step(st, e[k], kp, ki, kd, 1.0, dt, 1e9)
    e_prev = e[498]
    positional = kp * e[499] + ki * dt * e.sum() + kd * (e[499] - e_prev) / dt
    assert u == pytest.approx(positional, rel=1e-9)


def test_bppid_gains_stay_in_range_and_learn_deterministically():
    def run():
        st = records()[1]["ctl"]["bppid"]
        rng = np.random.default_rng(3)
        gains = []
        for _ in range(3000):
            control.bppid_step(PR["control"], st, rng.normal(0, 0.6), 0.001)
            gains.append(st["gains"].copy())
        return st, np.array(gains)

    a, ga = run()
    b, gb = run()
    assert np.array_equal(ga, gb)
    assert np.all(ga > 0) and np.all(ga < P.control.bp_scale)
    assert not np.allclose(a["w_o"], P.control.bp_w_out)   # it learned
    # learning lowers the BA error: after its first transient (K_i dips in the first few
    # hundred ticks) the integral (skyhook) gain grows. (Its end against its start depended
    # on where in its range the design puts the start: 92 % of it on the default car.)
    late = ga[1000:, 1]
    assert np.polyfit(np.arange(late.size), late, 1)[0] > 0


def test_bppid_turns_no_body_motion_into_a_static_force():
    """The network's gains follow BA; a PID that took them as they are within a body cycle
    rectified BA (its integral term K_i(BA) e dt has a mean), a static force that lowered the
    body. The PID takes them low-passed: over a minute of a 1.2 Hz body motion its force has
    no mean to speak of. (With the gains as they are, alpha = 1, the same drive leaves a mean
    of a sixth of the force's RMS: what this test would catch.)"""
    dt = 0.001
    t = np.arange(60_000) * dt
    ba = 0.6 * np.sin(2 * np.pi * 1.2 * t) + np.random.default_rng(5).normal(0, 0.05, len(t))

    def force(c):
        rec, state = records(dataclasses.replace(P, control=c))
        st = state["ctl"]["bppid"]
        u = np.array([control.bppid_step(rec["control"], st, a, dt) for a in ba])[20_000:]
        return abs(u.mean()) / np.sqrt(np.mean(u ** 2))

    assert P.control.bp_gain_alpha < 0.01
    assert force(P.control) < 0.01                     # (measured: 0.08 N on 143 N RMS)
    assert force(dataclasses.replace(P.control, bp_gain_alpha=1.0)) > 0.1   # (-23 N)


def test_bppid_derivatives_errata_13():
    x = np.linspace(-3, 3, 13)
    g = 0.5 * (1 + np.tanh(x))
    assert np.allclose(g, np.exp(x) / (np.exp(x) + np.exp(-x)))
    h = 1e-6
    gp = (0.5 * (1 + np.tanh(x + h)) - 0.5 * (1 + np.tanh(x - h))) / (2 * h)
    assert np.allclose(gp, 2 * g * (1 - g), atol=1e-8)
    f = np.tanh(x)
    fp_num = (np.tanh(x + h) - np.tanh(x - h)) / (2 * h)
    assert np.allclose(fp_num, 1 - f ** 2, atol=1e-8)


def test_ecu_is_deterministic():
    def run():
        e = Ecu(P)
        rng = np.random.default_rng(9)
        outs = []
        for k in range(2000):
            r = raw(body_accel=int(2048 + rng.integers(-30, 30)), wheel_accel=int(2048 + rng.integers(-100, 100)),
                    susp_defl=int(2048 + rng.integers(-50, 50)), speed=2000)
            outs.append(e.step(Inputs(k, *r, fp.REQ_CHOOSE, fp.MODE_COMFORT, 1)))
        return outs

    assert run() == run()


def test_paper_table2_rule():
    from firmware.grade import paper_rule

    g = P.grade
    G = PR["grade"]
    assert paper_rule(G, 0.5 * g.dtd1, 0.5 * g.ba1) == 0          # A: energy feedback
    assert paper_rule(G, 0.5 * g.dtd1, 1.0 * g.ba1) == 1          # B: BA >= threshold
    assert paper_rule(G, 1.0 * g.dtd1, g.ba2) == 2                # C: DTD >= threshold, BA <= ba2
    assert paper_rule(G, 2.0 * g.dtd1, 1.01 * g.ba2) == 3         # D
    assert g.ba1 < g.ba2                                          # B@10 below C@30, from the model


def test_sil_refuses_an_ecu_tick_that_differs_from_the_plant_step():
    from hil.nodes import sil
    from calib.options import DesignOptions
    from hil.sim.road import constant_route

    other = build(default_vehicle(), DesignOptions(dt_s=0.002))
    with pytest.raises(ValueError, match="plant step"):
        sil.run(default_vehicle(), constant_route("B", 20.0, 1.0), "comfort", 1, params=other)
