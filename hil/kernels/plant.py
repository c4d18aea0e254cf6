"""The plant's compiled kernels (``hil.sim.plant`` is the model): the active corner's exact step with
its energy ledger in one call, the accelerations and what the sensors see, the passive twin's
batch run, the energy quadratic forms. Explicit loops in a fixed order (``firmware.kernels``):
the same bits compiled or interpreted."""

from __future__ import annotations

import math

import numpy as np

from firmware.kernels import njit

N_AUG = 10
VS, VT, ZS, ZT, CUR, ZF, VOLT, ZFDOT, FB, FW = range(N_AUG)

# The ledger's running sums, in the compiled step's accumulator array (hil.sim.plant.QuarterCarPlant._acc).
ACC = ("road_in_j", "nonlinear_work_j", "supply_drawn_j", "stored_j", "copper_loss_j",
       "damper_loss_j", "friction_loss_j", "screw_loss_j", "flyback_loss_j", "electromagnetic_j",
       "actuator_mech_j", "final_mech_j", "final_inductor_j")
(A_ROAD, A_NL, A_SUPPLY, A_STORED, A_CU, A_DAMPER, A_FRIC, A_SCREW, A_FLYBACK, A_EM, A_ACT,
 A_MECH, A_IND) = range(len(ACC))


(P_MS, P_MT, P_KS, P_CS, P_KT, P_K, P_B, P_ETA, P_CLEAR, P_KB, P_LOAD, P_BUMP, P_LIFT, P_IMAX,
 P_SAG) = range(15)


@njit
def nonlinear(x, zf, pp):
    """Bump-stop force on the body and the wheel, tyre lift-off force on the wheel."""
    fb = fw = 0.0
    contact = lifted = False
    zs, zt = x[2], x[3]
    if pp[P_BUMP] != 0.0:
        d = zs - zt + pp[P_SAG]             # (from the ride height: the static sag too)
        over = abs(d) - pp[P_CLEAR]
        if over > 0.0:
            f = -pp[P_KB] * over * math.copysign(1.0, d)
            fb += f
            fw -= f
            contact = True
    if pp[P_LIFT] != 0.0:
        total = pp[P_LOAD] + pp[P_KT] * (zf - zt)
        if total < 0.0:
            fw -= total
            lifted = True
    return fb, fw, contact, lifted


@njit
def actuator_force(x, pp):
    vrel = x[0] - x[1]
    g = pp[P_ETA] if pp[P_K] * x[4] * vrel >= 0.0 else 1.0 / pp[P_ETA]
    return g * pp[P_K] * x[4] - pp[P_B] * vrel


@njit
def accelerations(x, zf, pp, has_actuator):
    vs, vt, zs, zt = x[0], x[1], x[2], x[3]
    fb, fw, _, _ = nonlinear(x, zf, pp)
    f_act = actuator_force(x, pp) if has_actuator else 0.0
    spring_damper = pp[P_KS] * (zs - zt) + pp[P_CS] * (vs - vt)
    ba = (-spring_damper + f_act + fb) / pp[P_MS]
    wa = (spring_damper - f_act - pp[P_KT] * (zt - zf) + fw) / pp[P_MT]
    return ba, wa


@njit
def sensed(x, zf, pp, has_actuator):
    ba, wa = accelerations(x, zf, pp, has_actuator)
    return ba, wa, x[2] - x[3] + pp[P_SAG], x[4]


# what observe_into writes, per row
OBS = ("ba", "wa", "sws", "dtd", "force", "stored", "drawn")


@njit
def observe_into(x, zf, pp, has_actuator, acc, out, k):
    out[k, 0], out[k, 1] = accelerations(x, zf, pp, has_actuator)
    out[k, 2] = x[2] - x[3]
    out[k, 3] = x[3] - zf
    out[k, 4] = actuator_force(x, pp) if has_actuator else 0.0
    out[k, 5] = acc[A_STORED]
    out[k, 6] = acc[A_SUPPLY]


@njit
def step(phi, x, zf, zf_next, volt, v_dc, enabled, dt, pp):
    """One exact step: zeta(t+dt) = phi zeta(t), with the bridge's current limit. Returns
    (x after the step, zeta over the step, current limited, bump contact, tyre lifted)."""
    zeta = np.empty(N_AUG)
    new = np.empty(5)
    limited, contact, lifted = step_into(phi, x, zf, zf_next, volt, v_dc, enabled, dt, pp,
                                         zeta, new)
    return new, zeta, limited, contact, lifted


@njit
def step_into(phi, x, zf, zf_next, volt, v_dc, enabled, dt, pp, zeta, new):
    """``step`` into ``zeta`` and ``new`` (x after the step; it may be ``x`` itself: x is read
    into zeta first). Returns (current limited, bump contact, tyre lifted)."""
    fb, fw, contact, lifted = nonlinear(x, zf, pp)
    for i in range(5):
        zeta[i] = x[i]
    zeta[ZF] = zf
    zeta[VOLT] = volt
    zeta[ZFDOT] = (zf_next - zf) / dt
    zeta[FB] = fb
    zeta[FW] = fw
    limited = False
    if enabled:
        # hardware current limit: the end-of-step current is affine in the voltage
        base = 0.0
        for j in range(N_AUG):
            base += phi[CUR, j] * zeta[j]
        base -= phi[CUR, VOLT] * volt
        i_end = base + phi[CUR, VOLT] * volt
        if abs(i_end) > pp[P_IMAX]:
            lim = (math.copysign(pp[P_IMAX], i_end) - base) / phi[CUR, VOLT]
            zeta[VOLT] = min(v_dc, max(-v_dc, lim))
            limited = True
    for i in range(5):
        s = 0.0
        for j in range(N_AUG):
            s += phi[i, j] * zeta[j]
        new[i] = s
    return limited, contact, lifted


@njit
def advance(phis, flows, x, zf, zf_next, duty, regen, enabled, dt, pp, v, ind_l, track, acc):
    """``QuarterCarPlant.step`` after its input checks: the bridge, the discretisation of the
    efficiency branch, the exact step and (``track``) the ledger's sums in ``acc``. Returns
    (x after the step, current limited, bump contact, tyre lifted)."""
    new = x.copy()
    limited, contact, lifted = advance_into(phis, flows, new, zf, zf_next, duty, regen,
                                            enabled, dt, pp, v, ind_l, track, acc,
                                            np.empty(N_AUG), np.empty(flows.shape[2]))
    return new, limited, contact, lifted


@njit
def advance_into(phis, flows, x, zf, zf_next, duty, regen, enabled, dt, pp, v, ind_l, track,
                 acc, zeta, q):
    """``advance`` with the state ``x`` stepped in place and its scratch given (``zeta``:
    N_AUG, ``q``: one per energy flow): no allocation. Returns (current limited, bump
    contact, tyre lifted)."""
    if not enabled and x[4] != 0.0:         # the bridge opens: the inductor's energy is dumped
        acc[A_FLYBACK] += inductor_energy(x[4], ind_l)
        x[4] = 0.0
    motoring = is_motoring(x, pp) if enabled else True
    e, m = int(enabled), int(motoring)
    v_dc = v[1] if regen else v[0]
    volt = duty * v_dc if enabled else 0.0
    limited, contact, lifted = step_into(phis[e, m], x, zf, zf_next, volt, v_dc, enabled, dt,
                                         pp, zeta, x)
    if track:
        quadratic_forms_into(flows[e, m], zeta, q)
        acc[A_ROAD] += q[0]
        acc[A_NL] += q[1]
        if regen:
            acc[A_STORED] -= q[2]
        else:
            acc[A_SUPPLY] += q[2]
        acc[A_CU] += q[3]
        acc[A_DAMPER] += q[4]
        acc[A_FRIC] += q[5]
        acc[A_EM] += q[6]
        acc[A_ACT] += q[7]
        acc[A_SCREW] += q[6] - q[7]
        acc[A_MECH] = mech_energy(x, zf_next, pp)
        acc[A_IND] = inductor_energy(x[4], ind_l)
    return limited, contact, lifted


@njit
def mech_energy(x, zf, pp):
    """Kinetic energy of both masses plus the spring's and the tyre's."""
    vs, vt, zs, zt = x[0], x[1], x[2], x[3]
    return 0.5 * (pp[P_MS] * vs * vs + pp[P_MT] * vt * vt + pp[P_KS] * (zs - zt) ** 2
                  + pp[P_KT] * (zt - zf) ** 2)


@njit
def inductor_energy(i, ind_l):
    return 0.5 * ind_l * i ** 2


@njit
def is_motoring(x, pp):
    """The motor drives the screw (K i v_rel >= 0): efficiency eta, else 1/eta."""
    return pp[P_K] * x[4] * (x[0] - x[1]) >= 0.0


@njit
def quadratic_forms(flows, zeta):
    """flows @ outer(zeta, zeta).ravel(): the step's energy flows."""
    out = np.empty(flows.shape[0])
    quadratic_forms_into(flows, zeta, out)
    return out


@njit
def quadratic_forms_into(flows, zeta, out) -> None:
    n = zeta.shape[0]
    for f in range(flows.shape[0]):
        s = 0.0
        for a in range(n):
            for b in range(n):
                s += flows[f, a * n + b] * (zeta[a] * zeta[b])
        out[f] = s


@njit
def run_open(phi, x, zf, zf_next, dt, pp, has_actuator, contact, lifted, out, flags):
    contacts = lifts = 0
    for k in range(zf_next.shape[0]):
        x, _, _, c, li = step(phi, x, zf, zf_next[k], 0.0, 0.0, False, dt, pp)
        if c and not contact:
            contacts += 1
        if li and not lifted:
            lifts += 1
        contact, lifted = c, li
        zf = zf_next[k]
        out[0, k], _ = accelerations(x, zf, pp, has_actuator)
        out[1, k] = x[2] - x[3]
        out[2, k] = x[3] - zf
        out[3, k] = x[0] - x[1]
        flags[0, k] = c
        flags[1, k] = li
    return x, zf, contacts, lifts
