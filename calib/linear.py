"""Exact stationary statistics of the linear quarter car and the physical limits of control.

* Passive and closed-loop RMS values come from the continuous Lyapunov equation
  ``A_cl P + P A_cl^T + G G^T = 0`` (no simulation, no sampling error).
* LQR with the full state (road state included) and the cross term N (BA contains the force)
  minimises any weighted sum of the output variances over *all* causal controllers, because the
  plant is linear and the road input Gaussian. The set of achievable variance triples is convex,
  so every constrained optimum is reached by LQR for some weights, and the Lagrange dual over
  the weights is exact (no duality gap). ``limits`` maximises that dual.

Variances are normalised by the passive car's, so the problems are scale-free (independent of
the grade; the speed enters only through the road pole f0 = n_c v).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import solve_continuous_are
from scipy.optimize import minimize

from calib.model import (LinearModel, output_covariance, passive_rms, state_covariance,
                         window_covariance, window_scatter)

# Regularisers in scaled units (every passive variance is 1): a tiny weight on the force and on
# every state keeps the Riccati equation well posed at the corners of the weight space (e.g. no
# SWS weight, where the BA-cancelling force would leave the body free). They change the limits
# by about 1e-9.
_EPS_R = 1e-9
_EPS_Q = 1e-9


def _care_eig(A: np.ndarray, B: np.ndarray, Q: np.ndarray, R: float) -> np.ndarray:
    """Stabilising ARE solution from the stable eigenvectors of the Hamiltonian (no cross
    term). More tolerant than the QZ reordering of eigenvalues close to the imaginary axis."""
    n = A.shape[0]
    H = np.block([[A, -np.outer(B, B) / R], [-Q, -A.T]])
    w, V = np.linalg.eig(H)
    stable = np.argsort(w.real)[:n]
    if np.any(w.real[stable] >= 0.0):
        raise ValueError("Hamiltonian has no stable n-dimensional subspace")
    U = V[:, stable]
    P = np.real(U[n:] @ np.linalg.inv(U[:n]))
    return 0.5 * (P + P.T)


def lqr_gain(model: LinearModel, weights: np.ndarray, r: float = 0.0,
             q_state: float = 0.0) -> np.ndarray:
    """K minimising E[sum_i w_i y_i^2 + r u^2 + q_state |x|^2] with y = C x + D u
    (cross term N = C^T W D)."""
    W = np.diag(np.asarray(weights, dtype=float))
    Q = model.C.T @ W @ model.C + q_state * np.eye(model.A.shape[0])
    R = float(model.D @ W @ model.D) + r
    if R <= 0.0:
        raise ValueError("LQR needs a positive force weight (weight on BA or r > 0)")
    N = model.C.T @ W @ model.D
    B = model.B.reshape(-1, 1)
    try:
        P = solve_continuous_are(model.A, B, 0.5 * (Q + Q.T), np.array([[R]]), s=N.reshape(-1, 1))
    except (ValueError, np.linalg.LinAlgError):
        # remove the cross term (A - B N^T / R, Q - N N^T / R) and use the eigenvector method
        Ab = model.A - np.outer(model.B, N) / R
        Qb = Q - np.outer(N, N) / R
        P = _care_eig(Ab, model.B, 0.5 * (Qb + Qb.T), R)
    K = ((B.T @ P + N.reshape(1, -1)) / R).ravel()
    if np.max(np.linalg.eigvals(model.A - np.outer(model.B, K)).real) >= 0.0:
        raise ValueError("LQR solution is not stabilising")
    return K


@dataclass
class Normalised:
    """The model rescaled for numerical conditioning: outputs divided by their passive RMS
    (passive variances are all 1), states by their passive standard deviation, and the force
    by m_s * BA_passive. ``physical_gain`` maps a gain back to u = -K x in SI units."""

    model: LinearModel
    passive: np.ndarray   # passive RMS of [BA, SWS, DTD], SI units
    state_scale: np.ndarray
    force_scale: float

    @classmethod
    def of(cls, model: LinearModel) -> "Normalised":
        P = state_covariance(model.A, model.G)
        passive = passive_rms(model)
        T = np.sqrt(np.diag(P))
        Ti = np.diag(1.0 / T)
        S = np.diag(1.0 / passive)
        su = 1.0 / abs(model.D[0] / passive[0])  # force giving one passive BA RMS
        scaled = LinearModel(Ti @ model.A @ np.diag(T), Ti @ model.B * su, Ti @ model.G,
                             S @ model.C @ np.diag(T), S @ model.D * su)
        return cls(scaled, passive, T, su)

    def physical_gain(self, K: np.ndarray) -> np.ndarray:
        return self.force_scale * K / self.state_scale

    def lqr(self, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(K in scaled units, normalised variances) of the LQR for these weights (any
        positive scale: they are normalised to sum 1, which the regularisers refer to)."""
        weights = np.asarray(weights, dtype=float)
        weights = weights / weights.sum()
        for q_state in (_EPS_Q, 1e3 * _EPS_Q, 1e5 * _EPS_Q):
            try:
                K = lqr_gain(self.model, weights, _EPS_R, q_state)
                break
            except ValueError:
                # a corner of the weight space where the Hamiltonian has modes near the
                # imaginary axis: a larger (still negligible) state weight moves them off it
                continue
        else:
            raise ValueError(f"LQR has no stabilising solution for weights {weights}")
        var, _ = output_covariance(self.model, K)
        return K, var


def _dual_max(norm: Normalised, objective: int, bounds: tuple[float, float] = (1.0, 1.0)
              ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """min J_obj s.t. RMS ratio_i <= bound_i for the other two outputs, by maximising the
    Lagrange dual g(lam) = min_K J_obj + sum lam_i (J_i - c_i) over lam >= 0 (Danskin:
    grad = J_i - c_i), c_i = bound_i^2."""
    others = [i for i in range(3) if i != objective]
    c = np.asarray(bounds, dtype=float) ** 2

    def neg_dual(lam: np.ndarray) -> tuple[float, np.ndarray]:
        w = np.zeros(3)
        w[objective] = 1.0
        w[others] = lam
        _, var = norm.lqr(w)
        g = var[objective] + float(lam @ (var[others] - c))
        return -g, -(var[others] - c)

    best = None
    for start in ([1.0, 1.0], [0.1, 3.0], [3.0, 0.1]):
        res = minimize(neg_dual, np.array(start), jac=True, method="L-BFGS-B",
                       bounds=[(LAM_MIN, 1e6)] * 2,
                       options={"ftol": 1e-15, "gtol": 1e-12, "maxiter": 500})
        if best is None or res.fun < best.fun:
            best = res
    lam = _kkt_polish(norm, objective, others, c, np.array(best.x, dtype=float))
    w = np.zeros(3)
    w[objective] = 1.0
    w[others] = lam
    K, var = norm.lqr(w)
    return var[objective] + float(lam @ (var[others] - c)), w, K, var


LAM_MIN = 1e-6              # the multipliers' lower bound (an inactive bound's multiplier)
KKT_TOL = 1e-14             # the active bounds' residual the polish stops at (normalised)


def _kkt_polish(norm: Normalised, objective: int, others: list[int], c: np.ndarray,
                lam: np.ndarray) -> np.ndarray:
    """The dual's maximiser to the last bits the Lyapunov solves carry: Newton's method on the
    active bounds' equations var_i(lam) = c_i (i with lam_i above ``LAM_MIN``; the others stay
    at it), from L-BFGS-B's point. L-BFGS-B stops on a tolerance of the dual's value, which is
    flat at its maximum (it is quadratic there): its multipliers differed by 4e-7 (relative)
    between two BLAS kernels, and the designs built on them in their 7th digit. Solving the
    active bounds' equations instead pins the multipliers to about the Lyapunov solves'
    rounding over the equations' slope (1e-13 relative on the shipped cars). The Jacobian is a
    central difference (relative step 1e-6); the iterate with the smallest residual is kept."""
    active = [j for j in range(len(lam)) if lam[j] > LAM_MIN * (1.0 + 1e-9)]
    if not active:
        return lam

    def resid(x: np.ndarray) -> np.ndarray:
        w = np.zeros(3)
        w[objective] = 1.0
        w[others] = x
        _, var = norm.lqr(w)
        return (var[others] - c)[active]

    best_x, best_r = lam.copy(), resid(lam)
    x, r = best_x.copy(), best_r
    for _ in range(12):
        if float(np.max(np.abs(r))) <= KKT_TOL:
            break
        J = np.empty((len(active), len(active)))
        for col, j in enumerate(active):
            h = 1e-6 * x[j]
            xp, xm = x.copy(), x.copy()
            xp[j] += h
            xm[j] -= h
            J[:, col] = (resid(xp) - resid(xm)) / (2.0 * h)
        try:
            step = np.linalg.solve(J, r)
        except np.linalg.LinAlgError:
            break
        x_new = x.copy()
        x_new[active] = np.clip(x[active] - step, LAM_MIN, 1e6)
        r_new = resid(x_new)
        if not float(np.max(np.abs(r_new))) < float(np.max(np.abs(r))):
            break
        x, r = x_new, r_new
        if float(np.max(np.abs(r))) < float(np.max(np.abs(best_r))):
            best_x, best_r = x.copy(), r
    return best_x


def _balanced(norm: Normalised) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """min_K max_i J_i = max over the simplex mu of min_K sum mu_i J_i (minimax duality)."""

    def neg_dual(theta: np.ndarray) -> float:
        mu = np.exp(theta - np.max(theta))
        mu /= mu.sum()
        _, var = norm.lqr(mu)
        return -float(mu @ var)

    best = None
    for start in ([0.0, 0.0, 0.0], [1.0, -1.0, 0.0], [-1.0, 1.0, 0.5]):
        res = minimize(neg_dual, np.array(start), method="Nelder-Mead",
                       options={"xatol": 1e-9, "fatol": 1e-13, "maxiter": 4000})
        if best is None or res.fun < best.fun:
            best = res
    mu = np.exp(best.x - np.max(best.x))
    mu /= mu.sum()
    K, var = norm.lqr(mu)
    return -best.fun, mu, K, var


def weights_from_log(z: np.ndarray) -> np.ndarray:
    """Normalised LQR weights (q1 = 1) from log10(q2/q1), log10(q3/q1)."""
    return np.array([1.0, 10.0 ** z[0], 10.0 ** z[1]])


def _eq43_min(norm: Normalised, bounds: np.ndarray | None = None
              ) -> tuple[float, np.ndarray, np.ndarray, np.ndarray]:
    """Minimum of Eq. (43) under (44) (each ratio <= 1, or <= ``bounds``) over the Pareto
    frontier, which LQR weights trace. The objective (a sum of square roots) is not convex:
    grid, then local refinement."""
    bounds = np.ones(3) if bounds is None else np.asarray(bounds, dtype=float)

    def f(z: np.ndarray, penalty: bool = True) -> float:
        _, var = norm.lqr(weights_from_log(z))
        ratios = np.sqrt(var)
        if penalty:
            return float(np.sum(ratios) + 100.0 * np.sum(np.maximum(ratios - bounds, 0.0)))
        return math.inf if np.any(ratios > bounds) else float(np.sum(ratios))

    grid = np.linspace(-3.0, 5.0, 21)
    scores = sorted((f(np.array([a, b])), a, b) for a in grid for b in grid)
    best_z, best_val = None, math.inf
    for _, a, b in scores[:4]:
        res = minimize(f, np.array([a, b]), method="Nelder-Mead",
                       options={"xatol": 1e-7, "fatol": 1e-12, "maxiter": 2000})
        val = f(res.x, penalty=False)
        if val < best_val:
            best_z, best_val = res.x, val
    if best_z is None:
        raise ValueError(f"no controller keeps every ratio within its bound {bounds.tolist()}")
    q = weights_from_log(best_z)
    K, var = norm.lqr(q)
    return best_val, q, K, var


@dataclass
class LimitResult:
    value: float              # the limit (ratio to passive, or Eq. (43) sum)
    weights: np.ndarray       # LQR output weights on normalised [BA, SWS, DTD] achieving it
    K: np.ndarray             # physical-units gain u = -K x
    ratios: np.ndarray        # RMS ratios to passive of [BA, SWS, DTD] at that K

    def as_dict(self) -> dict:
        return {"value": self.value, "weights": self.weights.tolist(), "K": self.K.tolist(),
                "ratios": {"ba": self.ratios[0], "sws": self.ratios[1], "dtd": self.ratios[2]}}


def physical_limits(model: LinearModel) -> dict[str, LimitResult]:
    """The exact limits of any causal controller with the full state (road included)."""
    norm = Normalised.of(model)

    def result(value: float, w: np.ndarray, K: np.ndarray, var: np.ndarray) -> LimitResult:
        return LimitResult(value, w, norm.physical_gain(K), np.sqrt(var))

    g, w, K, var = _dual_max(norm, objective=0)
    comfort = result(math.sqrt(g), w, K, var)
    g, w, K, var = _dual_max(norm, objective=2)
    safety = result(math.sqrt(g), w, K, var)
    t, mu, K, var = _balanced(norm)
    balanced = result(math.sqrt(t), mu, K, var)
    val, q, K, var = _eq43_min(norm)
    eq43 = result(val, q, K, var)
    return {"comfort": comfort, "safety": safety, "balanced": balanced, "eq43": eq43}



def constrained_limits(model: LinearModel, window_s: float, z: float = 3.0, steps: int = 40,
                       tol: float = 5e-4) -> dict[str, LimitResult]:
    """The comfort, safety and Eq. (43) limits under the per-drive bound: the best any causal
    controller (full state, as ``physical_limits``) reaches while each bounded ratio, measured
    over one drive of ``window_s`` seconds against the passive twin, stays at most 1 with ``z``
    sigma confidence: ratio_i <= exp(-z sigma_i(K)), sigma at the limit's own gain
    (``calib.model.window_scatter``). Comfort: min BA with SWS and DTD so bounded; safety:
    min DTD with BA and SWS; eq43: min the sum with all three (Eq. (44) under the bound). A
    fixed point: the bounds start at 1 and move to those the last gain's sigma sets until
    these are within ``tol`` of them; once a step overshoots (on a short drive the map
    oscillates, a tighter bound giving a gain that scatters less, with a slope near -0.5),
    the bounds move half way instead, a contraction of about 0.25. ValueError when no
    controller keeps the bounded ratios within their bounds (a drive too short for the
    per-drive bound) or no fixed point is reached."""
    norm = Normalised.of(model)
    out = {}
    for name, bounded in (("comfort", [1, 2]), ("safety", [0, 1]), ("eq43", [0, 1, 2])):
        bounds = np.ones(len(bounded))
        step, last = 1.0, None
        for _ in range(steps):
            if name == "eq43":
                value, w, K, var = _eq43_min(norm, bounds)
            else:
                g, w, K, var = _dual_max(norm, 0 if name == "comfort" else 2,
                                         (float(bounds[0]), float(bounds[1])))
                value = math.sqrt(g)
            gain = norm.physical_gain(K)
            _, sigma = window_scatter(model, gain, window_s)
            target = np.minimum(1.0, np.exp(-z * sigma[bounded]))
            move = target - bounds
            if bool(np.all(np.abs(move) <= tol)):
                break
            if last is not None and np.any(move * last < 0.0):
                step = 0.5
            bounds, last = bounds + step * move, move
        else:
            raise ValueError(f"constrained {name} limit: no fixed point of its bounds within "
                             f"{tol} after {steps} steps")
        out[name] = LimitResult(value, w, gain, np.sqrt(var))
    return out

# -- designs for the ECU: blind to the unobservable common mode -----------------------------

REL_T = np.array([[1.0, 0, 0, 0, 0], [0, 1.0, 0, 0, 0], [0, 0, 1.0, -1.0, 0], [0, 0, 0, 1.0, -1.0]])
_REL_S = np.array([[1.0, 0, 0, 0], [0, 1.0, 0, 0], [0, 0, 1.0, 1.0], [0, 0, 0, 1.0], [0, 0, 0, 0]])


def relative_model(model: LinearModel) -> LinearModel:
    """The model in relative coordinates r = [zs_dot, zt_dot, SWS, DTD] with the road as a
    random walk (its slow pole dropped): the road velocity is the white-noise input. The
    absolute heights, whose common mode the ECU cannot observe (errata 9), do not appear, so a
    gain designed here and lifted by ``REL_T`` has no component along the common mode."""
    A = model.A.copy()
    A[4, 4] = 0.0
    return LinearModel(REL_T @ A @ _REL_S, REL_T @ model.B, REL_T @ model.G, model.C @ _REL_S,
                       model.D.copy())


class RelativeFamily:
    """LQR gains designed on the relative model and lifted to the full state, evaluated
    exactly (Lyapunov) on the full model: the family the ECU's LQR controllers come from."""

    def __init__(self, model: LinearModel):
        self.model = model
        self.rel = Normalised.of(relative_model(model))
        self.passive_var, _ = output_covariance(model)

    def evaluate(self, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(K in SI units for the full state, RMS ratios to passive of [BA, SWS, DTD])."""
        K4, _ = self.rel.lqr(np.asarray(weights, dtype=float))
        K5 = self.rel.physical_gain(K4) @ REL_T
        var, _ = output_covariance(self.model, K5)
        return K5, np.sqrt(var / self.passive_var)


def safety_design(model: LinearModel, bound: float | tuple[float, float] = 1.0) -> LimitResult:
    """Safety-mode LQR for the ECU: min DTD with BA and SWS <= ``bound`` x passive (one
    bound for both, or (BA, SWS)), designed on the relative model (blind to the common mode)
    by the Lagrange dual, ratios computed exactly on the full model. (The comprehensive
    mode's GA-LQR comes from ``tools.tune_ga_lqr`` over the same family.)"""
    bounds = (bound, bound) if np.isscalar(bound) else tuple(bound)
    return _relative_design(model, 2, bounds)


def comfort_design(model: LinearModel, bounds: tuple[float, float] = (1.0, 1.0)) -> LimitResult:
    """Comfort-mode state feedback for the ECU: min BA with SWS and DTD <= ``bounds`` x
    passive, on the relative model (blind to the common mode) by the Lagrange dual, ratios
    computed exactly on the full model. Its gain shapes the suspension's stiffness and
    feeds back the tyre force; its body-velocity part is the skyhook the BP-PID adds."""
    return _relative_design(model, 0, bounds)


def _relative_design(model: LinearModel, objective: int, bounds: tuple[float, float]
                     ) -> LimitResult:
    """min the ``objective`` output with the other two <= ``bounds`` x passive, designed on
    the relative model by the Lagrange dual, ratios exact on the full model."""
    fam = RelativeFamily(model)
    _, w, _, _ = _dual_max(fam.rel, objective, bounds)
    K5, ratios = fam.evaluate(w)
    return LimitResult(float(ratios[objective]), w, K5, ratios)


# the value each limit bounds: its ratio's index, or None for Eq. (43)'s sum of the three
LIMIT_VALUE = {"comfort": 0, "safety": 2, "eq43": None}


def drive_scatter(model: LinearModel, name: str, K: np.ndarray, window_s: float) -> float:
    """The standard deviation of the value the limit ``name`` bounds (comfort: the BA ratio;
    safety: DTD; eq43: the sum of the three ratios), measured over one drive of ``window_s``
    seconds under u = -K x against the passive twin (to first order, from
    ``calib.model.window_covariance``): known before any run, it says how far one drive's
    ratio, or the mean of n drives' (divided by sqrt n), may fall from the exact value."""
    ratios, cov = window_covariance(model, K, window_s)
    i = LIMIT_VALUE[name]
    if i is not None:
        return float(ratios[i] * math.sqrt(max(cov[i, i], 0.0)))
    return float(math.sqrt(max(ratios @ cov @ ratios, 0.0)))
