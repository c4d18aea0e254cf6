"""Quarter-car plant with a ball-screw DC-motor actuator, exactly discretised.

Within one plant step (``dt``) the inputs are held: the H-bridge voltage (PWM duty times the DC
voltage, zero-order hold), the nonlinear correction forces (bump stops, tyre lift-off) and the
screw efficiency branch; the road height is linear in time between the tick positions
(first-order hold, the profile being piecewise linear). Under these holds the plant is linear
and time-invariant within the step, so the step is *exact*: the augmented state

    zeta = [zs_dot, zt_dot, zs, zt, i, zf, V, zf_dot, F_body, F_wheel]

obeys zeta' = M zeta (the last four are constant), and zeta(t+dt) = expm(M dt) zeta(t).
Every energy flow of the ledger is a quadratic form of zeta integrated over the step, which is
also exact (Van Loan's method), so the ledger balances to rounding error: a real check that the
electrical and mechanical sides of the model are consistent.

Actuator physics (in parallel with the spring and damper, force F up on the body, down on the
wheel): K = K_t * 2*pi/lead is the ideal force per ampere and the back-EMF per (m/s).
  L di/dt = V - R i - K (zs_dot - zt_dot)
  F = g K i - b (zs_dot - zt_dot)
The screw efficiency eta enters as g = eta when the motor drives the screw (K i v_rel >= 0) and
g = 1/eta when the suspension back-drives it (the screw needs more force per ampere), chosen at
the start of each step. The H-bridge has a hardware current limit: if the current at the end of
the step would exceed it, the bridge lowers its average voltage for that step so that it does
not. With the regen switch on, the bridge's DC side is the storage element instead of the bus.
With the bridge disabled the motor is open-circuited (i = 0; the inductor's energy is dumped in
the flyback path and booked as such).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from calib.exact import expm
from calib.model import mechanics, van_loan_integral
from calib.vehicle import VehicleConfig
from hil.kernels import plant as kern
from hil.kernels.plant import (ACC, A_MECH, A_STORED, A_SUPPLY, CUR, FB, FW, N_AUG, OBS, VOLT,  # noqa: F401
                               VS, VT, ZF, ZFDOT, ZT)

# Energy flows integrated exactly over each step (J): names of the quadratic forms.
FLOWS = ("road_in", "nonlinear_work", "dc", "copper_loss", "damper_loss", "friction_loss",
         "electromagnetic", "actuator_mech")


def _unit(i: int) -> np.ndarray:
    e = np.zeros(N_AUG)
    e[i] = 1.0
    return e


def _sym(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Symmetric Q with zeta^T Q zeta = (a.zeta)(b.zeta)."""
    outer = np.outer(a, b)
    return 0.5 * (outer + outer.T)


@dataclass
class _Discretisation:
    phi: np.ndarray       # (10, 10)
    flows: np.ndarray     # (len(FLOWS), 100): energies = flows @ outer(zeta, zeta).ravel()


@dataclass
class Ledger:
    """Cumulative energies (J). Inputs: road, nonlinear elements, DC supply. Everything else is
    where the energy went. ``balance_residual_j`` is inputs minus outputs."""

    road_in_j: float = 0.0
    nonlinear_work_j: float = 0.0
    supply_drawn_j: float = 0.0       # from the bus (regen switch off); negative = returned
    stored_j: float = 0.0             # into the storage element (regen switch on)
    copper_loss_j: float = 0.0
    damper_loss_j: float = 0.0
    friction_loss_j: float = 0.0
    screw_loss_j: float = 0.0
    flyback_loss_j: float = 0.0
    electromagnetic_j: float = 0.0    # converted electrical -> mechanical at the motor
    actuator_mech_j: float = 0.0      # delivered by the screw to the suspension
    initial_mech_j: float = 0.0
    initial_inductor_j: float = 0.0
    final_mech_j: float = 0.0
    final_inductor_j: float = 0.0
    extra: dict = field(default_factory=dict)

    @property
    def inputs_j(self) -> float:
        return self.road_in_j + self.nonlinear_work_j + self.supply_drawn_j

    @property
    def outputs_j(self) -> float:
        return ((self.final_mech_j - self.initial_mech_j)
                + (self.final_inductor_j - self.initial_inductor_j)
                + self.stored_j + self.copper_loss_j + self.damper_loss_j + self.friction_loss_j
                + self.screw_loss_j + self.flyback_loss_j)

    @property
    def balance_residual_j(self) -> float:
        return self.inputs_j - self.outputs_j

    @property
    def scale_j(self) -> float:
        return max(abs(self.road_in_j) + abs(self.nonlinear_work_j) + abs(self.supply_drawn_j)
                   + abs(self.stored_j), 1e-300)

    @property
    def relative_imbalance(self) -> float:
        return abs(self.balance_residual_j) / self.scale_j

    @property
    def electrical_residual_j(self) -> float:
        """DC side = copper + inductor + electromagnetic conversion (circuit check)."""
        dc = self.supply_drawn_j - self.stored_j
        return dc - (self.copper_loss_j + self.electromagnetic_j + self.flyback_loss_j
                     + self.final_inductor_j - self.initial_inductor_j)

    def as_dict(self) -> dict:
        keys = ("road_in_j", "nonlinear_work_j", "supply_drawn_j", "stored_j", "copper_loss_j",
                "damper_loss_j", "friction_loss_j", "screw_loss_j", "flyback_loss_j")
        out = {k: getattr(self, k) for k in keys}
        out["balance_residual_j"] = self.balance_residual_j
        out["relative_imbalance"] = self.relative_imbalance
        return out


class QuarterCarPlant:
    """The plant. ``actuator=False`` gives the passive car (no motor, no screw friction)."""

    # Back-EMF constant relative to the force constant. Physics says 1 (K_t = K_e in SI);
    # tests set another value to show that the energy ledger detects the inconsistency.
    _emf_scale = 1.0

    def __init__(self, cfg: VehicleConfig, *, actuator: bool = True, ledger: bool = False):
        self.cfg = cfg
        self.dt = cfg.sim.plant_dt_s
        self.has_actuator = actuator
        self.track_ledger = ledger
        vp, ap = cfg.vehicle, cfg.actuator
        self._ms, self._mt = vp.sprung_mass_kg, vp.unsprung_mass_kg
        self._ks, self._cs, self._kt = (vp.spring_stiffness_n_per_m, vp.damping_n_s_per_m,
                                        vp.tire_stiffness_n_per_m)
        self._K = ap.force_constant_n_per_a if actuator else 0.0
        self._b = ap.viscous_friction_n_s_per_m if actuator else 0.0
        self._eta = ap.screw_efficiency
        self._L, self._R = ap.winding_inductance_h, ap.winding_resistance_ohm
        self._imax = ap.current_limit_a
        self._tyre_load = vp.static_tire_load_n
        nl = cfg.nonlinear
        self._bump = nl.bump_stops
        self._clear, self._kb = nl.bump_stop_clearance_m, nl.bump_stop_stiffness_n_per_m
        self._lift = nl.tire_lift_off
        self._disc: dict[tuple[bool, bool], _Discretisation] = {}
        for enabled in (True, False):
            for motoring in (True, False):
                if enabled and not actuator:
                    continue
                self._disc[(enabled, motoring)] = self._discretise(enabled, motoring)
        # the same, stacked for the compiled step: [enabled, motoring] (a passive car never
        # uses enabled=True; its entries repeat the open bridge's)
        self._phis = np.empty((2, 2, N_AUG, N_AUG))
        self._flows = np.empty((2, 2, len(FLOWS), N_AUG * N_AUG))
        for enabled in (0, 1):
            for motoring in (0, 1):
                d = self._disc.get((bool(enabled), bool(motoring)),
                                   self._disc[(False, bool(motoring))])
                self._phis[enabled, motoring] = d.phi
                self._flows[enabled, motoring] = d.flows
        self._v = np.array([ap.bus_voltage_v, ap.storage_voltage_v])
        self.x = np.zeros(5)  # vs, vt, zs, zt, i
        self.zf = 0.0
        self._ledger = Ledger()
        self._acc = np.zeros(len(ACC))
        self.bump_contacts = 0
        self.lift_off_events = 0
        self.in_bump_contact = False
        self.tire_lifted = False
        self.current_limited_steps = 0
        self._last_g = self._eta
        # the kernels' parameters, in the order of the P_* indices
        self._pp = np.array([self._ms, self._mt, self._ks, self._cs, self._kt, self._K, self._b,
                             self._eta, self._clear, self._kb, self._tyre_load,
                             float(self._bump), float(self._lift), self._imax,
                             nl.static_deflection_m])

    # -- model -----------------------------------------------------------------------------
    def _matrix(self, enabled: bool, motoring: bool) -> np.ndarray:
        A4, b_force, b_road = mechanics(self.cfg.vehicle)
        g = self._eta if motoring else 1.0 / self._eta
        M = np.zeros((N_AUG, N_AUG))
        M[:4, :4] = A4
        # screw viscous friction acts like extra damping
        M[VS, VS] -= self._b / self._ms
        M[VS, VT] += self._b / self._ms
        M[VT, VS] += self._b / self._mt
        M[VT, VT] -= self._b / self._mt
        M[:4, CUR] = b_force * g * self._K
        M[:4, ZF] = b_road
        M[VS, FB] = 1.0 / self._ms
        M[VT, FW] = 1.0 / self._mt
        if enabled and self.has_actuator:
            M[CUR, VS] = -self._K * self._emf_scale / self._L
            M[CUR, VT] = self._K * self._emf_scale / self._L
            M[CUR, CUR] = -self._R / self._L
            M[CUR, VOLT] = 1.0 / self._L
        M[ZF, ZFDOT] = 1.0
        return M

    def _discretise(self, enabled: bool, motoring: bool) -> _Discretisation:
        M = self._matrix(enabled, motoring)
        g = self._eta if motoring else 1.0 / self._eta
        e = _unit
        vrel = e(VS) - e(VT)
        forms = {
            "road_in": self._kt * _sym(e(ZF) - e(ZT), e(ZFDOT)),
            "nonlinear_work": _sym(e(FB), e(VS)) + _sym(e(FW), e(VT)),
            "dc": _sym(e(VOLT), e(CUR)),
            "copper_loss": self._R * _sym(e(CUR), e(CUR)),
            "damper_loss": self._cs * _sym(vrel, vrel),
            "friction_loss": self._b * _sym(vrel, vrel),
            "electromagnetic": self._K * _sym(e(CUR), vrel),
            "actuator_mech": g * self._K * _sym(e(CUR), vrel),
        }
        flows = np.stack([van_loan_integral(M, forms[name], self.dt).ravel() for name in FLOWS])
        return _Discretisation(expm(M * self.dt), flows)

    # -- state -----------------------------------------------------------------------------
    def reset(self, zf0: float = 0.0) -> None:
        """Static equilibrium on a road at height ``zf0`` (deviations from it are zero)."""
        self.x = np.array([0.0, 0.0, zf0, zf0, 0.0])
        self.zf = float(zf0)
        self._ledger = Ledger()
        self._acc[:] = 0.0
        self._ledger.initial_mech_j = self._acc[A_MECH] = self.mech_energy_j()
        self.bump_contacts = self.lift_off_events = self.current_limited_steps = 0
        self.in_bump_contact = self.tire_lifted = False

    @property
    def ledger(self) -> Ledger:
        """The energy ledger (its running sums live in the compiled step's array)."""
        led = self._ledger
        for name, v in zip(ACC, self._acc.tolist()):
            setattr(led, name, v)
        return led

    @property
    def bus_voltage_v(self) -> float:
        """The H-bridge's DC supply now (the vehicle file's bus voltage unless a fault
        campaign dropped it: ``set_bus_voltage``)."""
        return float(self._v[0])

    def set_bus_voltage(self, volts: float) -> None:
        self._v[0] = volts

    @property
    def stored_j(self) -> float:
        return float(self._acc[A_STORED])

    @property
    def supply_drawn_j(self) -> float:
        return float(self._acc[A_SUPPLY])

    def mech_energy_j(self) -> float:
        return kern.mech_energy(self.x, self.zf, self._pp)

    def _nonlinear_forces(self) -> tuple[float, float, bool, bool]:
        return kern.nonlinear(self.x, self.zf, self._pp)

    def _motoring(self) -> bool:
        return kern.is_motoring(self.x, self._pp)

    def actuator_force_n(self) -> float:
        """Force of the actuator on the body (screw output minus its friction)."""
        if not self.has_actuator:
            return 0.0
        return kern.actuator_force(self.x, self._pp)

    def accelerations(self) -> tuple[float, float]:
        """Body and wheel acceleration now (m/s^2), with the current road height."""
        return kern.accelerations(self.x, self.zf, self._pp, self.has_actuator)

    def sensed(self) -> tuple[float, float, float, float]:
        """What the sensors see now, in one compiled call: body and wheel acceleration
        (``accelerations``), suspension deflection and motor current."""
        return kern.sensed(self.x, self.zf, self._pp, self.has_actuator)

    def observe_into(self, out: np.ndarray, k: int) -> None:
        """Write row ``k`` of ``out`` with the quantities ``OBS`` (in that order) in one
        compiled call: the same values as ``accelerations``, ``susp_defl_m``, ``tire_defl_m``,
        ``actuator_force_n``, ``stored_j`` and ``supply_drawn_j``."""
        kern.observe_into(self.x, self.zf, self._pp, self.has_actuator, self._acc, out, k)

    @property
    def susp_defl_m(self) -> float:
        return float(self.x[2] - self.x[3])

    @property
    def tire_defl_m(self) -> float:
        return float(self.x[3] - self.zf)

    @property
    def current_a(self) -> float:
        return float(self.x[4])

    # -- step ------------------------------------------------------------------------------
    def step(self, zf_next: float, duty: float = 0.0, regen: bool = False,
             enable: bool = True) -> None:
        """Advance one plant step to road height ``zf_next``.

        ``duty`` in [-1, 1] is the H-bridge's signed PWM duty (average voltage duty * V_dc),
        ``regen`` routes the bridge's DC side to the storage element, ``enable`` False opens the
        bridge (no current, no active force).
        """
        if not math.isfinite(duty):
            duty, enable = 0.0, False  # fail-safe: a non-finite command opens the bridge
        duty = min(1.0, max(-1.0, duty))
        enabled = bool(enable) and self.has_actuator
        self.x, limited, contact, lifted = kern.advance(
            self._phis, self._flows, self.x, self.zf, float(zf_next), duty, bool(regen), enabled,
            self.dt, self._pp, self._v, self._L, self.track_ledger, self._acc)
        if contact and not self.in_bump_contact:
            self.bump_contacts += 1
        if lifted and not self.tire_lifted:
            self.lift_off_events += 1
        self.in_bump_contact, self.tire_lifted = contact, lifted
        self.current_limited_steps += int(limited)
        self.zf = float(zf_next)

    def run_passive(self, zf_next: np.ndarray) -> dict:
        """Step the plant with the bridge open through the road heights ``zf_next`` in one
        compiled loop; the same arithmetic as that many ``step(z, enable=False)`` calls (the
        passive twin rides the whole road this way). Returns, per step, what ``step`` then
        ``accelerations`` give: ba, sws, dtd, vrel (and bump contact / lift-off flags)."""
        if self.track_ledger:
            raise ValueError("run_passive keeps no energy ledger")
        if self.x[4] != 0.0:            # the bridge opens: the inductor's energy is dumped
            self.x[4] = 0.0
        n = len(zf_next)
        out = np.empty((4, n))
        flags = np.empty((2, n), dtype=np.bool_)
        self.x, self.zf, contacts, lifts = kern.run_open(
            self._disc[(False, True)].phi, self.x, self.zf, np.asarray(zf_next, dtype=float),
            self.dt, self._pp, self.has_actuator, self.in_bump_contact, self.tire_lifted, out,
            flags)
        self.bump_contacts += contacts
        self.lift_off_events += lifts
        if n:
            self.in_bump_contact, self.tire_lifted = bool(flags[0, -1]), bool(flags[1, -1])
        return {"ba": out[0], "sws": out[1], "dtd": out[2], "vrel": out[3],
                "contact": flags[0], "lifted": flags[1]}
