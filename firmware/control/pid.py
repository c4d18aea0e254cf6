"""Incremental PID on the body acceleration (errata 13):

    du = K_p (e_k - e_{k-1}) + K_i e_k dt + K_d (e_k - 2 e_{k-1} + e_{k-2}) / dt
    u_k = leak * u_{k-1} + du

with e = r - y = -BA (reference: no body acceleration). The integral of -BA is minus the body
velocity, so K_i acts as skyhook damping; the leak (a time constant of seconds, far below the
body mode) keeps an accelerometer offset from winding the output up.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class PidState:
    e1: float = 0.0
    e2: float = 0.0
    u: float = 0.0


def terms(st: PidState, e: float, dt: float) -> tuple[float, float, float]:
    """The three increments that multiply K_p, K_i, K_d (also du/dK for the BP network)."""
    return e - st.e1, e * dt, (e - 2.0 * st.e1 + st.e2) / dt


def step(st: PidState, e: float, kp: float, ki: float, kd: float, leak: float, dt: float,
         limit: float) -> float:
    tp, ti, td = terms(st, e, dt)
    u = leak * st.u + kp * tp + ki * ti + kd * td
    st.u = min(limit, max(-limit, u))       # anti-windup: the state never exceeds the limit
    st.e2, st.e1 = st.e1, e
    return st.u


def reset_to(st: PidState, u: float) -> None:
    """Bumpless start from the force currently applied."""
    st.u = u
