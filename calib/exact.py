"""Design-time linear algebra that gives the same numbers on every x86-64 host.

numpy and scipy hand products and factorisations to OpenBLAS and LAPACK, whose kernels (chosen
for the CPU: ``Haswell``, ``SkylakeX``, ``Sandybridge``, ...) sum in different orders, so the
same call differs in its last bits from host to host. Most of the design is insensitive to
that, but some steps amplify it: a discrete Lyapunov or Riccati equation whose closed loop has
a pole near the unit circle (the isolation bank's voltage-offset state, a random walk: a
condition number near 1e7) turned 1e-16 in its inputs into 4e-9 in the bank's covariances.

Here the sensitive steps are computed so that their result no longer depends on the kernels:

* products in x87 extended precision (``np.longdouble``, a 64-bit mantissa): numpy computes
  those in its own loops, in index order, without BLAS, so the same inputs give the same bits
  on every x86-64 host (``matmul``);
* the matrix exponential by scaling and squaring of a Taylor series, in extended precision
  (``expm``): the model's discretisation (Phi, Gamma, Van Loan's integrals) bit-identical;
* discrete Lyapunov (Stein) equations by doubling, and the filters' Riccati equations by the
  structured doubling algorithm polished by Newton's method, both in extended precision and
  without LAPACK (``solve_stein``, ``dare_filter``): the same bits from the same inputs, where
  LAPACK's solutions differed by 4e-9 between two kernels;
* a continuous Lyapunov equation solved by LAPACK and refined by Newton's method with the
  residual in extended precision (``solve_lyap``): to about its condition number x 1e-19.

What is left of the host is below the calibration's grid (``calib.grid``), which rounds the
values a solver returns to 32 significant bits. (On a host whose ``long double`` is not the
x87 format the extended results differ; the project targets x86-64, docs/calibration.md.)
"""

from __future__ import annotations

import math

import numpy as np
from scipy.linalg import solve_continuous_lyapunov

LD = np.longdouble
REFINE_STEPS = 4            # Newton steps on a solve (each multiplies the error by ~1e-9)


def ld(a) -> np.ndarray:
    return np.asarray(a, dtype=LD)


def matmul(*mats) -> np.ndarray:
    """The product of the matrices (or vectors), in extended precision, in index order."""
    out = ld(mats[0])
    for m in mats[1:]:
        out = out @ ld(m)
    return out


def product(*mats) -> np.ndarray:
    """``matmul`` rounded to float64 (the same bits on every host)."""
    return np.asarray(matmul(*mats), dtype=float)


def closed_loop(phi: np.ndarray, K: np.ndarray, H: np.ndarray) -> np.ndarray:
    """Phi (I - K H), float64, computed in extended precision."""
    return product(phi, np.eye(phi.shape[0], dtype=LD) - matmul(K, H))


def expm(A: np.ndarray) -> np.ndarray:
    """e^A, float64: scaled by 2^-s to a norm at most 1/2, a Taylor series to the 24th power
    (remainder below 1e-31), squared s times, all in extended precision."""
    a = ld(A)
    n = a.shape[0]
    norm = float(np.max(np.sum(np.abs(a), axis=1))) if n else 0.0
    if not math.isfinite(norm):
        raise ValueError("expm of a matrix that is not finite")
    s = max(0, math.frexp(norm)[1] + 1) if norm > 0.0 else 0
    b = a / LD(2.0) ** s
    term = np.eye(n, dtype=LD)
    out = term.copy()
    for k in range(1, 25):
        term = term @ b / LD(k)
        out = out + term
    for _ in range(s):
        out = out @ out
    return np.asarray(out, dtype=float)


def solve_small(S: np.ndarray, B: np.ndarray) -> np.ndarray:
    """S^-1 B in extended precision (Gaussian elimination with partial pivoting, in a fixed
    order): for the few-by-few innovation covariances of the filters."""
    a, b = ld(S).copy(), ld(B).copy()
    vec = b.ndim == 1
    if vec:
        b = b[:, None]
    n = a.shape[0]
    for col in range(n):
        piv = col + int(np.argmax(np.abs(a[col:, col])))
        if a[piv, col] == 0:
            raise np.linalg.LinAlgError("singular matrix")
        if piv != col:
            a[[col, piv]] = a[[piv, col]]
            b[[col, piv]] = b[[piv, col]]
        for row in range(col + 1, n):
            f = a[row, col] / a[col, col]
            a[row, col:] -= f * a[col, col:]
            b[row] -= f * b[col]
    x = np.zeros_like(b)
    for row in range(n - 1, -1, -1):
        x[row] = (b[row] - a[row, row + 1:] @ x[row + 1:]) / a[row, row]
    return x[:, 0] if vec else x


def _refine(residual, correct, x0: np.ndarray, symmetric: bool) -> np.ndarray:
    """Newton's method: x += correct(x, residual(x)) with the residual in extended
    precision, until the correction vanishes or ``REFINE_STEPS``; symmetric solutions kept
    so."""
    x = ld(x0)
    for _ in range(REFINE_STEPS):
        r = residual(x)
        if not np.any(r):
            break
        e = ld(correct(x, r))
        x = x + e
        if symmetric:
            x = (x + x.T) / LD(2.0)
        if not np.any(np.asarray(e, dtype=float)):
            break
    return x


def solve_stein(A: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """X = A X A^T + Q (a discrete Lyapunov equation, A stable), float64: ``stein_ld``."""
    return np.asarray(stein_ld(A, Q), dtype=float)


def stein_ld(A, Q) -> np.ndarray:
    """X = A X A^T + Q in extended precision by doubling (Smith's method): X = sum_k A^k Q
    A^Tk, summed as X <- X + A X A^T, A <- A^2 until A^(2^j) vanishes against 2^-64 (the
    number of steps follows from the inputs alone: no LAPACK, no BLAS). LAPACK's direct
    solve (scipy) stalled here: the bank's filters have a pair of poles at |z| = 0.99996 and
    the absolute heights' common mode nearly fills X, and the Kronecker system's rcond was
    4e-17, so even refining its solution left 1e-12 between two BLAS kernels."""
    a, x = ld(A), ld(Q)
    if a.size and not float(np.max(np.abs(np.linalg.eigvals(np.asarray(A, dtype=float))))) < 1.0:
        raise ValueError("Stein equation: A is not stable")
    for _ in range(STEIN_MAX_DOUBLINGS):
        step = a @ x @ a.T
        x = x + step
        a = a @ a
        if not np.any(np.abs(a) > LD(2.0) ** -80):
            break
    else:
        raise ValueError("Stein equation: no convergence (a pole too close to the unit circle)")
    return (x + x.T) / LD(2.0)


STEIN_MAX_DOUBLINGS = 64    # 2^64 terms of the series: a pole within 1e-17 of the unit circle


def solve_lyap(A: np.ndarray, Q: np.ndarray) -> np.ndarray:
    """A X + X A^T + Q = 0 (a continuous Lyapunov equation), refined to extended precision."""
    a, q = ld(A), ld(Q)
    x = _refine(lambda x: a @ x + x @ a.T + q,
                lambda _, r: solve_continuous_lyapunov(A, -np.asarray(r, dtype=float)),
                solve_continuous_lyapunov(A, -Q), symmetric=True)
    return np.asarray(x, dtype=float)


def filter_gain(H: np.ndarray, P, R: np.ndarray) -> np.ndarray:
    """The Kalman filter's gain K = P H^T (H P H^T + R)^-1 for the predicted covariance P."""
    ph = ld(P) @ ld(H).T
    return solve_small(ld(H) @ ph + ld(R), ph.T).T


def dare_filter(phi: np.ndarray, H: np.ndarray, Q: np.ndarray, R: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """The steady-state Kalman filter of x+ = Phi x + w (cov Q), y = H x + v (cov R): (P, K),
    P the predicted covariance, K its gain, float64. The structured doubling algorithm (Chu,
    Fan and Lin 2005) on X = A^T X A - A^T X B (R + B^T X B)^-1 B^T X A + Q with A = Phi^T,
    B = H^T, in extended precision: A <- A W^-1 A, G <- G + A W^-1 G A^T, H <- H + A^T H
    W^-1 A with W = I + G H, from A = Phi^T, G = H^T R^-1 H, H = Q, until H stops changing
    (quadratic: some 25 steps for the bank's poles at |z| = 0.99996). No LAPACK: the same bits
    on every host, and no QZ reordering to fail (scipy's solve_discrete_are refused a car of
    the vehicle family on one host: "Reordering of (A, B) failed ... too far from generalized
    Schur form")."""
    n = phi.shape[0]
    eye = np.eye(n, dtype=LD)
    a = ld(phi).T
    g = ld(H).T @ solve_small(ld(R), ld(H))
    h = ld(Q)
    for _ in range(DARE_MAX_STEPS):
        z = solve_small(eye + g @ h, np.hstack([a, g]))
        za, zg = z[:, :n], z[:, n:]
        h_new = h + a.T @ h @ za
        g = g + a @ zg @ a.T
        a = a @ za
        h_new = (h_new + h_new.T) / LD(2.0)
        g = (g + g.T) / LD(2.0)
        done = not np.any(np.abs(h_new - h) > LD(2.0) ** -62 * np.max(np.abs(h_new)))
        h = h_new
        if done:
            break
    else:
        raise ValueError("Riccati equation: no convergence (an unstable or undetectable mode)")
    if not np.all(np.isfinite(np.asarray(h, dtype=float))):
        raise ValueError("Riccati equation: no finite solution")
    p = _newton_dare(phi, H, Q, R, h)
    return np.asarray(p, dtype=float), np.asarray(filter_gain(H, p, R), dtype=float)


def _newton_dare(phi, H, Q, R, p0) -> np.ndarray:
    """Newton's method (Hewer's) from the doubling's solution: with K of the current P and
    A_e = Phi (I - K H), the residual of the Joseph form A_e P A_e^T + Phi K R K^T Phi^T + Q
    - P (stationary in K) and its correction from one Stein equation (``stein_ld``). The
    doubling's residual, 1e-13 of P, drops to the extended precision's."""
    p_, h_, q_, r_ = ld(phi), ld(H), ld(Q), ld(R)
    eye = np.eye(phi.shape[0], dtype=LD)

    def closed(p):
        k = filter_gain(H, p, R)
        return k, p_ @ (eye - k @ h_)

    def residual(p):
        k, a_e = closed(p)
        return a_e @ p @ a_e.T + p_ @ k @ r_ @ k.T @ p_.T + q_ - p

    def correct(p, r):
        return stein_ld(np.asarray(closed(p)[1], dtype=float), r)

    return _refine(residual, correct, p0, symmetric=True)


DARE_MAX_STEPS = 64
