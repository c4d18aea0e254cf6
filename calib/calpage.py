"""The writable calibration outside a running ECU: a design file's ``[calibration]`` table.

A calibration engineer tunes the working page over XCP (``hil.xcp``); ``python -m hil xcp
save`` writes what differs from the reference page as a design file whose ``[calibration]``
table names each object as the A2L does without its ``cal.`` prefix::

    [calibration]
    "control.k_safety" = [-812.5, 95.0, 10250.0, -3300.0, 0.0]
    "modes.safety_hold_ticks" = 3000

``--design FILE`` reads it back: the ECU is built as the design says, then each value is set
as an XCP write sets it (the field whole, checked finite and inside the same limits as the
A2L's, which follow from the design's value: ``calib.calpage.WRITABLE``), so the run starts on
what the working page held. Only ``WRITABLE`` objects may be named.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from calib.errors import ConfigError


def _like(current, value):
    if isinstance(current, np.ndarray):
        return np.array(value, dtype=current.dtype).reshape(current.shape)
    if isinstance(current, bool):
        return bool(value)
    if isinstance(current, int):
        return int(value)
    if isinstance(current, float):
        return float(value)
    if isinstance(current, tuple):
        return tuple(type(c)(v) for c, v in zip(current, np.ravel(value)))
    raise TypeError(f"cannot set a {type(current).__name__}")


def replace_path(obj, path: tuple, value):
    """``obj`` (nested frozen dataclasses) with the field at ``path`` set to ``value``."""
    head = getattr(obj, path[0])
    new = _like(head, value) if len(path) == 1 else replace_path(head, path[1:], value)
    return dataclasses.replace(obj, **{path[0]: new})


def value_of(obj, path: tuple):
    for p in path:
        obj = getattr(obj, p)
    return obj


def _sym(v: float) -> tuple[float, float]:
    return -v, v


# The writable calibration: path -> (limits from the design value v (an array), unit, text).
# ``mag`` is the largest magnitude of the design value (1 where it is 0).
def _gain(v, mag):
    return _sym(4.0 * mag)


def _up4(v, mag):
    return 0.0, 4.0 * mag


def _unit_rate(v, mag):
    return 0.0, 1.0


def _around(v, mag):
    return 0.25 * float(np.min(v)), 4.0 * float(np.max(v))


def _only_down(v, mag):           # a limit: never above the design's
    return 0.0, float(np.max(v))


def _earlier(v, mag):             # a safety threshold: only towards earlier entry
    return 0.25 * float(np.min(v)), float(np.max(v))


def _longer(v, mag):              # a safety hold: only longer
    return float(np.min(v)), 4.0 * float(np.max(v))


def _forget(v, mag):
    return min(0.9, float(np.min(v))), 1.0


WRITABLE = {
    "control.k_safety": (_gain, "N/SI", "safety LQR gain row over [zs', zt', zs, zt, zf]"),
    "control.k_comprehensive": (_gain, "N/SI", "GA-LQR gain row over [zs', zt', zs, zt, zf]"),
    "control.k_comfort": (_gain, "N/SI", "comfort LQR gain row over [zs', zt', zs, zt, zf]"),
    "control.skyhook_c": (_up4, "N.s/m", "skyhook damping"),
    "control.skyhook_passive_c": (_up4, "N.s/m", "passive-mode skyhook damping"),
    "control.pid_kp": (_up4, "N.s^2/m", "PID proportional gain (on body acceleration)"),
    "control.pid_ki": (_up4, "N.s/m", "PID integral gain"),
    "control.pid_kd": (_up4, "N.s^3/m", "PID derivative gain"),
    "control.pid_leak": (_unit_rate, "", "PID integrator leak"),
    "control.bp_w_hidden": (_gain, "", "BP-PID initial hidden weights"),
    "control.bp_b_hidden": (_gain, "", "BP-PID initial hidden biases"),
    "control.bp_w_out": (_gain, "", "BP-PID initial output weights"),
    "control.bp_b_out": (_gain, "", "BP-PID initial output biases"),
    "control.bp_eta": (_unit_rate, "", "BP-PID learning rate"),
    "control.bp_alpha": (_unit_rate, "", "BP-PID momentum"),
    "control.bp_scale": (_up4, "", "BP-PID gain scales [kp, ki, kd]"),
    "control.bp_input_scale": (_around, "m/s^2", "BP-PID input scale"),
    "control.bp_gain_alpha": (_unit_rate, "", "BP-PID gain smoothing"),
    "control.regen_c": (_up4, "N.s/m", "regeneration damping"),
    "control.regen_skyhook_c": (_up4, "N.s/m", "regeneration skyhook damping"),
    "control.regen_min_voltage_ratio": (_unit_rate, "", "regeneration's minimum EMF ratio"),
    "control.force_limit": (_only_down, "N", "actuator force limit"),
    "actuator.ki": (_up4, "V/(A.s)", "current loop integral gain"),
    "actuator.current_limit": (_only_down, "A", "current limit"),
    "grade.hysteresis": (_up4, "grade", "grade hysteresis (log4 of Gq)"),
    "grade.dwell_ticks": (_around, "tick", "grade dwell"),
    "grade.min_speed": (_up4, "m/s", "grade estimation's minimum speed"),
    "grade.dtd1": (_around, "m", "tyre deflection threshold (mode logic)"),
    "grade.ba1": (_around, "m/s^2", "body acceleration lower threshold"),
    "grade.ba2": (_around, "m/s^2", "body acceleration upper threshold"),
    "modes.ramp_ticks": (_up4, "tick", "controller hand-over ramp"),
    "modes.request_min_ticks": (_up4, "tick", "driver request's minimum spacing"),
    "modes.safety_dtd_rms_limit": (_earlier, "m", "safety entry: tyre deflection RMS"),
    "modes.safety_exit_ratio": (_earlier, "", "safety exit below limit x ratio"),
    "modes.safety_hold_ticks": (_longer, "tick", "safety hold"),
    "akf.forgetting": (_forget, "", "Sage-Husa forgetting factor"),
    "akf.r_floor": (_around, "SI^2", "measurement noise floor [BA, SWS, WA]"),
    "akf.road_intensity_per_mps": (_around, "m^2/s^2", "road input intensity per m/s"),
    "akf.lift_force_sigma_n": (_around, "N", "force noise while a wheel lifts"),
    "akf.current_force_sigma_n": (_around, "N", "force noise without a current"),
    "akf.stroke_force_sigma_n": (_around, "N", "force noise at the bump stops"),
    "akf_q_gq_nominal": (_around, "m^3", "nominal road intensity Gq"),
}


def limits(name: str, design_value) -> tuple[float, float]:
    """The [lower, upper] a writable object may take, from its design value."""
    v = np.asarray(design_value, dtype=float)
    mag = float(np.max(np.abs(v))) or 1.0
    return WRITABLE[name][0](v, mag)


GAIN_ROWS = ("control.k_safety", "control.k_comprehensive", "control.k_comfort")


def unstable(p, name: str, K) -> str | None:
    """Why the state feedback u = -K x of the gain row ``name`` must not be written (None:
    it may): the closed loop on the ECU's own discretised model, Phi - Gamma K (the AKF's),
    has a pole on or outside the unit circle. (The A2L's limits let a gain go to 4x; the
    default car's safety row is unstable from 1.2x.)"""
    if name not in GAIN_ROWS:
        return None
    a = p.akf
    radius = float(np.max(np.abs(np.linalg.eigvals(a.phi - np.outer(a.gamma, K)))))
    if not radius < 1.0:
        return (f"{name}: the closed loop on the ECU's model is unstable (largest pole "
                f"|z| = {radius:.5f})")
    return None


def check_table(path, table) -> tuple:
    """A ``[calibration]`` table as ``DesignOptions.calibration``: ((name, values), ...)
    sorted by name, each value a tuple of finite numbers. An unknown name or a value that is
    not a number or a list of numbers is a ConfigError naming the file and the key."""
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: 'calibration' must be a table")
    out = []
    for name, value in sorted(table.items()):
        where = f"{path}: key 'calibration.\"{name}\"'"
        if name not in WRITABLE:
            raise ConfigError(f"{where}: not a writable calibration object (one of "
                              f"{', '.join(sorted(WRITABLE)[:4])}, ...: docs/xcp.md)")
        values = value if isinstance(value, list) else [value]
        if not values or not all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                 and math.isfinite(v) for v in values):
            raise ConfigError(f"{where} must be a finite number or a list of them")
        out.append((name, tuple(float(v) for v in values)))
    return tuple(out)


def refusal(reference, name: str, values) -> str | None:
    """Why ``values`` must not be written into the writable object ``name`` (None: they
    may), by the checks every write passes, over XCP (``hil.xcp.memory``) or from a design
    file (``apply``): the object's size, every element finite and inside its limits, a whole
    number where the field is an integer, and a gain row's closed loop stable. The limits
    follow from the ``reference`` parameters (the design as built, as the A2L's do), never
    from a working page: repeated writes would otherwise ratchet them."""
    current = value_of(reference, tuple(name.split(".")))
    v = np.ravel(np.asarray(values, dtype=float))
    size = int(np.size(current))
    if v.size != size:
        return f"{name}: {v.size} values, the object has {size}"
    if not np.all(np.isfinite(v)):
        return f"{name}: not a finite number"
    lo, hi = limits(name, current)
    if v.min() < lo or v.max() > hi:
        return f"{name}: {v.tolist()} outside [{lo:g}, {hi:g}] (the A2L's limits)"
    if np.issubdtype(np.asarray(current).dtype, np.integer) and np.any(v != np.round(v)):
        return f"{name}: must be a whole number"
    return unstable(reference, name, v)


def apply(p, calibration: tuple):
    """``p`` (``EcuParams``) with each (name, values) of a ``[calibration]`` table set; a
    value ``refusal`` refuses (its limits from ``p`` as given) is a ConfigError."""
    reference = p
    for name, values in calibration:
        why = refusal(reference, name, values)
        if why:
            raise ConfigError(f"design [calibration] {why}")
        path = tuple(name.split("."))
        current = value_of(p, path)
        p = replace_path(p, path, np.asarray(values).reshape(np.shape(current))
                         if np.ndim(current) else values[0])
    return p


def design_text(calibration: dict, base=None, header: str = "") -> str:
    """A design file: the ``[design]`` table of the design file ``base`` (the run's, checked
    by the caller with ``calib.options.load_options``; None: the defaults), and
    ``[calibration]``: ``base``'s, with ``calibration`` ({name: number or list}) over it.
    Numbers are written as Python's repr, so they read back bit for bit."""
    import tomli_w

    from calib.errors import read_toml

    doc = read_toml(base, "design") if base is not None else {}
    table = dict(doc.get("calibration", {}))
    table.update(calibration)
    out = {}
    if doc.get("design"):
        out["design"] = doc["design"]
    out["calibration"] = dict(sorted(table.items()))
    lines = "".join(f"# {line}\n" for line in header.splitlines())
    return lines + tomli_w.dumps(out)
