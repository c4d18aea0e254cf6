"""The adaptive Kalman filter's compiled kernels (``firmware.akf`` calls them): explicit loops
in a fixed order, a Jacobi eigen-decomposition for the R-hat guard, the adjugate (or Gaussian
elimination) for S^-1; no numpy/LAPACK call per tick, the same bits compiled or interpreted.
The state's arrays are updated in place by the ``*_into`` kernels: returning new arrays from a
compiled call costs about 1 us each in boxing.

The compiled tick (``firmware``) allocates nothing: ``predict_ws``, ``gain_ws``,
``update_ws`` and ``tick_ws`` work in a workspace record (``workspace_dtype``: every
intermediate matrix, sized by the measurements m and the states n; ``workspace`` makes one
for a Python caller)."""

from __future__ import annotations

import math

import numpy as np

from firmware.kernels import njit

R_CEILING = 1e8   # largest R-hat eigenvalue, in units of the floor
JACOBI_SWEEPS = 60



def workspace_dtype(m: int, n: int = 5) -> np.dtype:
    """The intermediates of one filter tick, for ``*_ws``."""
    return np.dtype([
        ("xn", "f8", (n,)), ("t1", "f8", (n, n)), ("t2", "f8", (n, n)), ("z", "f8", (m,)),
        ("resid", "f8", (m,)), ("K", "f8", (n, m)), ("eps", "f8", (m,)), ("hph", "f8", (m,)),
        ("HP", "f8", (m, n)), ("HPHt", "f8", (m, m)), ("Ra", "f8", (m, m)),
        ("S", "f8", (m, m)), ("Y", "f8", (m, n)), ("KHP", "f8", (n, n)), ("KS", "f8", (n, m)),
        ("KSKt", "f8", (n, n)), ("Pj", "f8", (n, n)),
        ("Rg", "f8", (m, m)), ("ja", "f8", (m, m)), ("jV", "f8", (m, m)), ("jw", "f8", (m,)),
        ("M", "f8", (m, m)),
    ])


def workspace(m: int, n: int = 5):
    """A workspace record for Python callers (its fields as attributes)."""
    return np.zeros(1, workspace_dtype(m, n)).view(np.recarray)[0]


@njit
def guard_ws(R, floor, scale, out, Rn, a, V, w):
    """guard_r into ``out`` (``Rn``, ``a``, ``V``, ``w``: scratch of R's size); returns whether
    it acted."""
    m = R.shape[0]
    total = 0.0
    for i in range(m):
        for j in range(m):
            out[i, j] = 0.5 * (R[i, j] + R[j, i])
            total += out[i, j]
    if not math.isfinite(total):          # a NaN or inf anywhere (finite R sums finite)
        for i in range(m):
            for j in range(m):
                out[i, j] = floor[i] if i == j else 0.0
        return True
    for i in range(m):
        for j in range(m):
            Rn[i, j] = out[i, j] / scale[i, j]
    if psd_shifted(Rn):                  # (implies trace >= n; the ceiling is checked inside)
        return False
    jacobi_into(Rn, a, V, w)
    for k in range(m):
        w[k] = min(R_CEILING, max(1.0, w[k]))
    for i in range(m):
        for j in range(m):
            s = 0.0
            for k in range(m):
                s += V[i, k] * w[k] * V[j, k]
            out[i, j] = s * scale[i, j]
    return True


@njit
def guard(R, floor, scale, out):
    """guard_r into ``out``; returns whether it acted."""
    m = R.shape[0]
    return guard_ws(R, floor, scale, out, np.empty((m, m)), np.empty((m, m)),
                    np.empty((m, m)), np.empty(m))


@njit
def psd_shifted(Rn) -> bool:
    """Is Rn - I positive semi-definite with trace(Rn) <= R_CEILING? All principal minors
    >= 0 in closed form for the 2x2 and 3x3 cases the ECU has; other sizes use the
    eigenvalues."""
    n = Rn.shape[0]
    if n == 3:
        a, b, c = Rn[0, 0], Rn[0, 1], Rn[0, 2]
        e, f, i = Rn[1, 1], Rn[1, 2], Rn[2, 2]
        if a + e + i > R_CEILING:
            return False
        a, e, i = a - 1.0, e - 1.0, i - 1.0
        if a < 0.0 or e < 0.0 or i < 0.0:
            return False
        if a * e - b * b < 0.0 or a * i - c * c < 0.0 or e * i - f * f < 0.0:
            return False
        return a * (e * i - f * f) - b * (b * i - f * c) + c * (b * f - e * c) >= 0.0
    if n == 2:
        a, b, e = Rn[0, 0], Rn[0, 1], Rn[1, 1]
        if a + e > R_CEILING:
            return False
        a, e = a - 1.0, e - 1.0
        return a >= 0.0 and e >= 0.0 and a * e - b * b >= 0.0
    tr = 0.0
    for k in range(n):
        tr += Rn[k, k]
    if not tr <= R_CEILING:
        return False
    w, _ = jacobi_eigh(Rn)
    for k in range(n):
        if w[k] < 1.0:
            return False
    return True


@njit
def jacobi_into(A, a, V, w):
    """Eigenvalues ``w`` and orthonormal eigenvectors ``V`` (columns) of the symmetric matrix
    A, by cyclic Jacobi rotations (A = V diag(w) V^T; ``a``: scratch). For the ECU's 2x2/3x3
    R-hat: a few sweeps, plain floats, the same bits compiled or interpreted."""
    n = A.shape[0]
    for i in range(n):
        for j in range(n):
            a[i, j] = A[i, j]
            V[i, j] = 0.0
    for k in range(n):
        V[k, k] = 1.0
    for _ in range(JACOBI_SWEEPS):
        off = 0.0
        diag = 0.0
        for p in range(n):
            diag += a[p, p] * a[p, p]
            for q in range(p + 1, n):
                off += a[p, q] * a[p, q]
        if not off > 1e-36 * diag:       # converged (or nothing finite left to rotate)
            break
        for p in range(n - 1):
            for q in range(p + 1, n):
                apq = a[p, q]
                if apq == 0.0:
                    continue
                theta = (a[q, q] - a[p, p]) / (2.0 * apq)
                if abs(theta) > 1e150:
                    t = 0.5 / theta
                else:
                    t = 1.0 / (abs(theta) + math.sqrt(theta * theta + 1.0))
                    if theta < 0.0:
                        t = -t
                c = 1.0 / math.sqrt(t * t + 1.0)
                s = t * c
                for k in range(n):        # A <- A J (columns p, q)
                    akp, akq = a[k, p], a[k, q]
                    a[k, p] = c * akp - s * akq
                    a[k, q] = s * akp + c * akq
                for k in range(n):        # A <- J^T A (rows p, q)
                    apk, aqk = a[p, k], a[q, k]
                    a[p, k] = c * apk - s * aqk
                    a[q, k] = s * apk + c * aqk
                for k in range(n):
                    vkp, vkq = V[k, p], V[k, q]
                    V[k, p] = c * vkp - s * vkq
                    V[k, q] = s * vkp + c * vkq
    for k in range(n):
        w[k] = a[k, k]


@njit
def jacobi_eigh(A):
    """``jacobi_into``, returning (w, V)."""
    n = A.shape[0]
    w, V = np.empty(n), np.empty((n, n))
    jacobi_into(A, np.empty((n, n)), V, w)
    return w, V


@njit
def solve_into(S, B, out, M):
    """S^-1 B into ``out`` for the symmetric positive definite innovation covariance S (the
    guard keeps it well conditioned): the adjugate for 3x3 and 2x2, Gaussian elimination with
    partial pivoting otherwise (and when the determinant is not positive; ``M``: scratch of
    S's size). A singular S gives NaN, which the ECU's non-finite check catches."""
    n, cols = B.shape
    if n == 3:
        a, b, c = S[0, 0], S[0, 1], S[0, 2]
        e, f, i = S[1, 1], S[1, 2], S[2, 2]
        A, Bc, C = e * i - f * f, c * f - b * i, b * f - c * e
        E, F, I = a * i - c * c, b * c - a * f, a * e - b * b
        det = a * A + b * Bc + c * C
        if det > 0.0 and math.isfinite(det):
            for j in range(cols):
                b0, b1, b2 = B[0, j], B[1, j], B[2, j]
                out[0, j] = (A * b0 + Bc * b1 + C * b2) / det
                out[1, j] = (Bc * b0 + E * b1 + F * b2) / det
                out[2, j] = (C * b0 + F * b1 + I * b2) / det
            return
    elif n == 2:
        a, b, e = S[0, 0], S[0, 1], S[1, 1]
        det = a * e - b * b
        if det > 0.0 and math.isfinite(det):
            for j in range(cols):
                out[0, j] = (e * B[0, j] - b * B[1, j]) / det
                out[1, j] = (a * B[1, j] - b * B[0, j]) / det
            return
    for i in range(n):
        for j in range(n):
            M[i, j] = S[i, j]
    for i in range(n):
        for j in range(cols):
            out[i, j] = B[i, j]
    for k in range(n):
        piv = k
        for i in range(k + 1, n):
            if abs(M[i, k]) > abs(M[piv, k]):
                piv = i
        if not abs(M[piv, k]) > 0.0:     # singular (or NaN): no solution
            out[:, :] = math.nan
            return
        if piv != k:
            for j in range(n):
                M[k, j], M[piv, j] = M[piv, j], M[k, j]
            for j in range(cols):
                out[k, j], out[piv, j] = out[piv, j], out[k, j]
        for i in range(k + 1, n):
            f = M[i, k] / M[k, k]
            for j in range(k, n):
                M[i, j] -= f * M[k, j]
            for j in range(cols):
                out[i, j] -= f * out[k, j]
    for k in range(n - 1, -1, -1):
        for j in range(cols):
            s = out[k, j]
            for i in range(k + 1, n):
                s -= M[k, i] * out[i, j]
            out[k, j] = s / M[k, k]


@njit
def solve_sym(S, B):
    """``solve_into``, returning S^-1 B."""
    n = S.shape[0]
    out = np.empty((n, B.shape[1]))
    solve_into(S, B, out, np.empty((n, n)))
    return out


@njit
def mm_into(A, B, out):
    """A @ B, summed in index order."""
    for i in range(A.shape[0]):
        for j in range(B.shape[1]):
            s = 0.0
            for k in range(A.shape[1]):
                s += A[i, k] * B[k, j]
            out[i, j] = s


@njit
def mmt_into(A, B, out):
    """A @ B.T, summed in index order."""
    for i in range(A.shape[0]):
        for j in range(B.shape[0]):
            s = 0.0
            for k in range(A.shape[1]):
                s += A[i, k] * B[j, k]
            out[i, j] = s


@njit
def predict_ws(phi, gamma, q_unit, x, P, u, q, with_x, W):
    """In place: x = phi x + gamma u (when ``with_x``), P = phi P phi^T + q q_unit."""
    n = P.shape[0]
    if with_x:
        for i in range(n):
            s = 0.0
            for j in range(n):
                s += phi[i, j] * x[j]
            W.xn[i] = s + gamma[i] * u
        for i in range(n):
            x[i] = W.xn[i]
    mm_into(phi, P, W.t1)
    mmt_into(W.t1, phi, W.t2)
    for i in range(n):
        for j in range(n):
            P[i, j] = W.t2[i, j] + q * q_unit[i, j]


@njit
def gain_ws(H, P, R, r, resid, r_floor, r_scale, b_pow, b, adaptive, bias_adaptive, W):
    """In place: the correction's noise adaptation (R, r), gain (``W.K``), innovation
    (``W.eps``), diag(H P H^T) (``W.hph``) and Joseph-form covariance (P); see
    ``firmware.akf.gain``. Returns (b_pow, guard acted)."""
    m, n = H.shape
    eps = W.eps
    for i in range(m):
        eps[i] = resid[i] - r[i] if bias_adaptive else resid[i]
    HP, HPHt = W.HP, W.HPHt
    mm_into(H, P, HP)
    mmt_into(HP, H, HPHt)
    hit = False
    if adaptive:
        d = (1.0 - b) / (1.0 - b_pow)      # b_pow = b^(t+1); d = 1 at t = 0
        b_pow *= b
        Ra = W.Ra
        for i in range(m):
            for j in range(m):
                Ra[i, j] = (1.0 - d) * R[i, j] + d * (eps[i] * eps[j] - HPHt[i, j])
        if bias_adaptive:
            for i in range(m):
                r[i] = (1.0 - d) * r[i] + d * resid[i]
        hit = guard_ws(Ra, r_floor, r_scale, R, W.Rg, W.ja, W.jV, W.jw)
    S = W.S
    for i in range(m):
        for j in range(m):
            S[i, j] = HPHt[i, j] + R[i, j]
    Y, K = W.Y, W.K
    solve_into(S, HP, Y, W.M)             # S^-1 H P; K = P H^T S^-1 = Y^T (S symmetric)
    for i in range(n):
        for j in range(m):
            K[i, j] = Y[j, i]
    # Joseph form (I-KH) P (I-KH)^T + K R K^T, expanded: P - K HP - (K HP)^T + K S K^T
    KHP, KSKt, Pj = W.KHP, W.KSKt, W.Pj
    mm_into(K, HP, KHP)
    mm_into(K, S, W.KS)
    mmt_into(W.KS, K, KSKt)
    for i in range(n):
        for j in range(n):
            Pj[i, j] = P[i, j] - KHP[i, j] - KHP[j, i] + KSKt[i, j]
    for i in range(n):
        for j in range(n):
            P[i, j] = 0.5 * (Pj[i, j] + Pj[j, i])
    for i in range(m):
        W.hph[i] = HPHt[i, i]
    return b_pow, hit


@njit
def update_ws(H, D, P, R, r, x, z, u, r_floor, r_scale, b_pow, b, adaptive, bias_adaptive,
              W):
    """In place: the residual z - H x - D u, ``gain_ws``, x += K eps. Returns (b_pow, guard
    acted)."""
    m, n = H.shape
    resid = W.resid
    for i in range(m):
        s = 0.0
        for k in range(n):
            s += H[i, k] * x[k]
        resid[i] = z[i] - s - D[i] * u
    b_pow, hit = gain_ws(H, P, R, r, resid, r_floor, r_scale, b_pow, b, adaptive,
                         bias_adaptive, W)
    K, eps = W.K, W.eps
    for i in range(n):
        s = 0.0
        for k in range(m):
            s += K[i, k] * eps[k]
        W.xn[i] = x[i] + s
    for i in range(n):
        x[i] = W.xn[i]
    return b_pow, hit


@njit
def tick_ws(phi, gamma, q_unit, H, D, P, R, r, x, u_tick, q, z0, z1, z2, u_now, r_floor,
            r_scale, b_pow, b, adaptive, bias_adaptive, eps_out, hph_out, W):
    """``predict_ws`` then ``update_ws`` with z = [z0, z1(, z2)]; the innovation and
    diag(H P H^T) into ``eps_out``, ``hph_out``. Returns (b_pow, guard acted, finite)."""
    predict_ws(phi, gamma, q_unit, x, P, u_tick, q, True, W)
    z = W.z
    z[0] = z0
    z[1] = z1
    if z.shape[0] > 2:
        z[2] = z2
    b_pow, hit = update_ws(H, D, P, R, r, x, z, u_now, r_floor, r_scale, b_pow, b, adaptive,
                           bias_adaptive, W)
    for i in range(eps_out.shape[0]):
        eps_out[i] = W.eps[i]
        hph_out[i] = W.hph[i]
    return b_pow, hit, all_finite(x, P)


@njit
def all_finite(x, P) -> bool:
    """No NaN or inf in the state or the covariance."""
    for i in range(x.shape[0]):
        if not math.isfinite(x[i]):
            return False
    for i in range(P.shape[0]):
        for j in range(P.shape[1]):
            if not math.isfinite(P[i, j]):
                return False
    return True
