/* See akf_cov.h. Each function mirrors the one of the same name in firmware/kernels/akf.py;
 * sums run in index order from zero, products and differences in the order Python writes
 * them (the bits depend on it). */
#include "akf_cov.h"

#include <math.h>

#define N 5
#define M AKF_M

#ifdef AKF_FLOAT
#define C(x) (x##f)
#define SQRT sqrtf
#define FLOOR floorf
#define FABS fabsf
#define LDEXP ldexpf
#define THETA_BIG 1e18f       /* theta^2 + 1 stays finite in float32 */
#define JACOBI_TOL 1.5e-14f   /* about FLT_EPSILON^2: float32 rotations reach no less */
#else
#define C(x) (x)
#define SQRT sqrt
#define FLOOR floor
#define FABS fabs
#define LDEXP ldexp
#define THETA_BIG 1e150
#define JACOBI_TOL 1e-36
#endif

static const akf_real phi[N * N] = AKF_PHI_F64;
static const akf_real q_unit[N * N] = AKF_Q_UNIT_F64;
static const akf_real gamma_[N] = AKF_GAMMA_F64;
static const akf_real gamma_wheel[N] = AKF_GAMMA_WHEEL_F64;
static const akf_real H[M * N] = AKF_H_F64;
static const akf_real r0[M * M] = AKF_R0_F64;
static const akf_real r_floor[M] = AKF_R_FLOOR_F64;
static const akf_real r_scale[M * M] = AKF_R_SCALE_F64;
static const akf_real p0[N * N] = AKF_P0_F64;
#define FORGETTING ((akf_real)AKF_FORGETTING_F64)
#define LIFT_VAR ((akf_real)AKF_LIFT_FORCE_VAR_F64)
#define CURRENT_VAR ((akf_real)AKF_CURRENT_FORCE_VAR_F64)
#define STROKE_VAR ((akf_real)AKF_STROKE_FORCE_VAR_F64)
#define R_CEILING ((akf_real)AKF_R_CEILING_F64)
#define SKIP_SCALE ((akf_real)AKF_SKIP_SCALE_F64)

void akf_cov_init(akf_cov_t *a)
{
    int i, j;
    for (i = 0; i < N; i++)
        for (j = 0; j < N; j++) a->P[i][j] = p0[N * i + j];
    for (i = 0; i < M; i++) {
        for (j = 0; j < M; j++) a->R[i][j] = r0[M * i + j];
        a->r[i] = C(0.0);
        a->m_scale[i] = LDEXP(C(1.0), FX_MEAS_FRAC[i]);
        a->m_inv[i] = LDEXP(C(1.0), -FX_MEAS_FRAC[i]);
    }
    for (i = 0; i < N * M; i++) a->k_scale[i] = LDEXP(C(1.0), FX_K_Q31_FRAC[i]);
    a->b_pow = FORGETTING;
    a->guard_hits = 0;
}

/* firmware.fixedpoint.to_fixed: y = v 2^frac saturated to int32, rounded half away */
static int32_t to_fixed(akf_real v, akf_real scale)
{
    akf_real y = v * scale;
    if (y >= C(2147483647.5)) return INT32_MAX;
    if (y <= C(-2147483648.5)) return INT32_MIN;
    return (int32_t)(y >= C(0.0) ? FLOOR(y + C(0.5)) : -FLOOR(-y + C(0.5)));
}

/* P += s2 outer(g, g) (firmware.akf._add_outer) */
static void add_outer(akf_real P[N][N], akf_real s2, const akf_real *g)
{
    int i, j;
    for (i = 0; i < N; i++)
        for (j = 0; j < N; j++) P[i][j] = P[i][j] + s2 * (g[i] * g[j]);
}

/* ---------------------------------------------------------------- the guard of R-hat */

static int psd_shifted(akf_real Rn[M][M])
{
#if M == 3
    akf_real a = Rn[0][0], b = Rn[0][1], c = Rn[0][2];
    akf_real e = Rn[1][1], f = Rn[1][2], i = Rn[2][2];
    if (a + e + i > R_CEILING) return 0;
    a = a - C(1.0), e = e - C(1.0), i = i - C(1.0);
    if (a < C(0.0) || e < C(0.0) || i < C(0.0)) return 0;
    if (a * e - b * b < C(0.0) || a * i - c * c < C(0.0) || e * i - f * f < C(0.0)) return 0;
    return a * (e * i - f * f) - b * (b * i - f * c) + c * (b * f - e * c) >= C(0.0);
#elif M == 2
    akf_real a = Rn[0][0], b = Rn[0][1], e = Rn[1][1];
    if (a + e > R_CEILING) return 0;
    a = a - C(1.0), e = e - C(1.0);
    return a >= C(0.0) && e >= C(0.0) && a * e - b * b >= C(0.0);
#else
#error "the R-hat guard has the closed form for 2 or 3 measurements only"
#endif
}

static void jacobi(akf_real A[M][M], akf_real a[M][M], akf_real V[M][M], akf_real w[M])
{
    int i, j, k, p, q, sweep;
    for (i = 0; i < M; i++)
        for (j = 0; j < M; j++) a[i][j] = A[i][j], V[i][j] = C(0.0);
    for (k = 0; k < M; k++) V[k][k] = C(1.0);
    for (sweep = 0; sweep < AKF_JACOBI_SWEEPS; sweep++) {
        akf_real off = C(0.0), diag = C(0.0);
        for (p = 0; p < M; p++) {
            diag += a[p][p] * a[p][p];
            for (q = p + 1; q < M; q++) off += a[p][q] * a[p][q];
        }
        if (!(off > JACOBI_TOL * diag)) break;   /* converged (or nothing finite left) */
        for (p = 0; p < M - 1; p++) {
            for (q = p + 1; q < M; q++) {
                akf_real apq = a[p][q], theta, t, c, s;
                if (apq == C(0.0)) continue;
                theta = (a[q][q] - a[p][p]) / (C(2.0) * apq);
                if (FABS(theta) > THETA_BIG) {
                    t = C(0.5) / theta;
                } else {
                    t = C(1.0) / (FABS(theta) + SQRT(theta * theta + C(1.0)));
                    if (theta < C(0.0)) t = -t;
                }
                c = C(1.0) / SQRT(t * t + C(1.0));
                s = t * c;
                for (k = 0; k < M; k++) {     /* A <- A J (columns p, q) */
                    akf_real akp = a[k][p], akq = a[k][q];
                    a[k][p] = c * akp - s * akq;
                    a[k][q] = s * akp + c * akq;
                }
                for (k = 0; k < M; k++) {     /* A <- J^T A (rows p, q) */
                    akf_real apk = a[p][k], aqk = a[q][k];
                    a[p][k] = c * apk - s * aqk;
                    a[q][k] = s * apk + c * aqk;
                }
                for (k = 0; k < M; k++) {
                    akf_real vkp = V[k][p], vkq = V[k][q];
                    V[k][p] = c * vkp - s * vkq;
                    V[k][q] = s * vkp + c * vkq;
                }
            }
        }
    }
    for (k = 0; k < M; k++) w[k] = a[k][k];
}

/* R-hat = the guarded Ra into out; returns whether the guard acted (guard_ws) */
static int guard(akf_real R[M][M], akf_real out[M][M], akf_ws_t *W)
{
    int i, j, k;
    akf_real total = C(0.0);
    for (i = 0; i < M; i++)
        for (j = 0; j < M; j++) {
            out[i][j] = C(0.5) * (R[i][j] + R[j][i]);
            total += out[i][j];
        }
    if (!isfinite(total)) {
        for (i = 0; i < M; i++)
            for (j = 0; j < M; j++) out[i][j] = i == j ? r_floor[i] : C(0.0);
        return 1;
    }
    for (i = 0; i < M; i++)
        for (j = 0; j < M; j++) W->Rg[i][j] = out[i][j] / r_scale[M * i + j];
    if (psd_shifted(W->Rg)) return 0;
    jacobi(W->Rg, W->ja, W->jV, W->jw);
    for (k = 0; k < M; k++) {
        akf_real v = W->jw[k] > C(1.0) ? W->jw[k] : C(1.0);
        W->jw[k] = v < R_CEILING ? v : R_CEILING;
    }
    for (i = 0; i < M; i++)
        for (j = 0; j < M; j++) {
            akf_real s = C(0.0);
            for (k = 0; k < M; k++) s += W->jV[i][k] * W->jw[k] * W->jV[j][k];
            out[i][j] = s * r_scale[M * i + j];
        }
    return 1;
}

/* ---------------------------------------------------------------- the gain */

/* Y = S^-1 B for B = H P (M x N): the adjugate, Gaussian elimination when the determinant is
 * not positive; a singular S gives NaN (solve_into) */
static void solve(akf_real S[M][M], akf_real B[M][N], akf_real out[M][N], akf_real Mx[M][M])
{
    int i, j, k, piv;
#if M == 3
    akf_real a = S[0][0], b = S[0][1], c = S[0][2];
    akf_real e = S[1][1], f = S[1][2], ii = S[2][2];
    akf_real A = e * ii - f * f, Bc = c * f - b * ii, Cc = b * f - c * e;
    akf_real E = a * ii - c * c, F = b * c - a * f, I = a * e - b * b;
    akf_real det = a * A + b * Bc + c * Cc;
    if (det > C(0.0) && isfinite(det)) {
        for (j = 0; j < N; j++) {
            akf_real b0 = B[0][j], b1 = B[1][j], b2 = B[2][j];
            out[0][j] = (A * b0 + Bc * b1 + Cc * b2) / det;
            out[1][j] = (Bc * b0 + E * b1 + F * b2) / det;
            out[2][j] = (Cc * b0 + F * b1 + I * b2) / det;
        }
        return;
    }
#elif M == 2
    akf_real a = S[0][0], b = S[0][1], e = S[1][1];
    akf_real det = a * e - b * b;
    if (det > C(0.0) && isfinite(det)) {
        for (j = 0; j < N; j++) {
            out[0][j] = (e * B[0][j] - b * B[1][j]) / det;
            out[1][j] = (a * B[1][j] - b * B[0][j]) / det;
        }
        return;
    }
#endif
    for (i = 0; i < M; i++)
        for (j = 0; j < M; j++) Mx[i][j] = S[i][j];
    for (i = 0; i < M; i++)
        for (j = 0; j < N; j++) out[i][j] = B[i][j];
    for (k = 0; k < M; k++) {
        piv = k;
        for (i = k + 1; i < M; i++)
            if (FABS(Mx[i][k]) > FABS(Mx[piv][k])) piv = i;
        if (!(FABS(Mx[piv][k]) > C(0.0))) {       /* singular (or NaN): no solution */
            for (i = 0; i < M; i++)
                for (j = 0; j < N; j++) out[i][j] = (akf_real)NAN;
            return;
        }
        if (piv != k) {
            for (j = 0; j < M; j++) {
                akf_real t = Mx[k][j];
                Mx[k][j] = Mx[piv][j], Mx[piv][j] = t;
            }
            for (j = 0; j < N; j++) {
                akf_real t = out[k][j];
                out[k][j] = out[piv][j], out[piv][j] = t;
            }
        }
        for (i = k + 1; i < M; i++) {
            akf_real f = Mx[i][k] / Mx[k][k];
            for (j = k; j < M; j++) Mx[i][j] = Mx[i][j] - f * Mx[k][j];
            for (j = 0; j < N; j++) out[i][j] = out[i][j] - f * out[k][j];
        }
    }
    for (k = M - 1; k >= 0; k--)
        for (j = 0; j < N; j++) {
            akf_real s = out[k][j];
            for (i = k + 1; i < M; i++) s = s - Mx[k][i] * out[i][j];
            out[k][j] = s / Mx[k][k];
        }
}

/* the noise adaptation, the gain and the Joseph update (gain_ws); returns the guard's act */
static int gain(akf_cov_t *a, int adaptive)
{
    akf_ws_t *W = &a->ws;
    int i, j, k, hit = 0;
    for (i = 0; i < M; i++) W->eps[i] = AKF_BIAS_ADAPTIVE ? W->resid[i] - a->r[i] : W->resid[i];
    for (i = 0; i < M; i++)
        for (j = 0; j < N; j++) {
            akf_real s = C(0.0);
            for (k = 0; k < N; k++) s += H[N * i + k] * a->P[k][j];
            W->HP[i][j] = s;
        }
    for (i = 0; i < M; i++)
        for (j = 0; j < M; j++) {
            akf_real s = C(0.0);
            for (k = 0; k < N; k++) s += W->HP[i][k] * H[N * j + k];
            W->HPHt[i][j] = s;
        }
    if (adaptive) {
        akf_real d = (C(1.0) - FORGETTING) / (C(1.0) - a->b_pow);   /* b_pow = b^(t+1) */
        a->b_pow *= FORGETTING;
        for (i = 0; i < M; i++)
            for (j = 0; j < M; j++)
                W->Ra[i][j] = (C(1.0) - d) * a->R[i][j]
                              + d * (W->eps[i] * W->eps[j] - W->HPHt[i][j]);
        if (AKF_BIAS_ADAPTIVE)
            for (i = 0; i < M; i++) a->r[i] = (C(1.0) - d) * a->r[i] + d * W->resid[i];
        hit = guard(W->Ra, a->R, W);
    }
    for (i = 0; i < M; i++)
        for (j = 0; j < M; j++) W->S[i][j] = W->HPHt[i][j] + a->R[i][j];
    solve(W->S, W->HP, W->Y, W->Mx);       /* S^-1 H P; K = P H^T S^-1 = Y^T */
    for (i = 0; i < N; i++)
        for (j = 0; j < M; j++) a->K[i][j] = W->Y[j][i];
    /* Joseph form, expanded: P - K HP - (K HP)^T + K S K^T */
    for (i = 0; i < N; i++)
        for (j = 0; j < N; j++) {
            akf_real s = C(0.0);
            for (k = 0; k < M; k++) s += a->K[i][k] * W->HP[k][j];
            W->KHP[i][j] = s;
        }
    for (i = 0; i < N; i++)
        for (j = 0; j < M; j++) {
            akf_real s = C(0.0);
            for (k = 0; k < M; k++) s += a->K[i][k] * W->S[k][j];
            W->KS[i][j] = s;
        }
    for (i = 0; i < N; i++)
        for (j = 0; j < N; j++) {
            akf_real s = C(0.0);
            for (k = 0; k < M; k++) s += W->KS[i][k] * a->K[j][k];
            W->KSKt[i][j] = s;
        }
    for (i = 0; i < N; i++)
        for (j = 0; j < N; j++)
            W->Pj[i][j] = a->P[i][j] - W->KHP[i][j] - W->KHP[j][i] + W->KSKt[i][j];
    for (i = 0; i < N; i++)
        for (j = 0; j < N; j++) a->P[i][j] = C(0.5) * (W->Pj[i][j] + W->Pj[j][i]);
    return hit;
}

/* P = phi P phi^T + q q_unit (predict_ws without x: the integer half predicts x) */
static void predict(akf_cov_t *a, akf_real q)
{
    akf_ws_t *W = &a->ws;
    int i, j, k;
    for (i = 0; i < N; i++)
        for (j = 0; j < N; j++) {
            akf_real s = C(0.0);
            for (k = 0; k < N; k++) s += phi[N * i + k] * a->P[k][j];
            W->t1[i][j] = s;
        }
    for (i = 0; i < N; i++)
        for (j = 0; j < N; j++) {
            akf_real s = C(0.0);
            for (k = 0; k < N; k++) s += W->t1[i][k] * phi[N * j + k];
            W->t2[i][j] = s;
        }
    for (i = 0; i < N; i++)
        for (j = 0; j < N; j++) a->P[i][j] = W->t2[i][j] + q * q_unit[N * i + j];
}

int akf_cov_step(akf_cov_t *a, akf_real q_road, int flags, const int32_t resid[AKF_M])
{
    akf_ws_t *W = &a->ws;
    int i, j, skip = flags & ((1 << M) - 1), adaptive;
    akf_real s2;
    /* the forces off the model (firmware.akf.unknown_forces) */
    if (flags & AKF_COV_LIFTED) add_outer(a->P, LIFT_VAR, gamma_wheel);
    s2 = ((flags & AKF_COV_CURRENT_UNKNOWN) ? CURRENT_VAR : C(0.0))
         + ((flags & AKF_COV_STROKE_UNKNOWN) ? STROKE_VAR : C(0.0));
    if (s2 > C(0.0)) add_outer(a->P, s2, gamma_);
    predict(a, q_road);
    for (j = 0; j < M; j++) {
        a->r_q[j] = isfinite(a->r[j]) ? to_fixed(a->r[j], a->m_scale[j]) : 0;
        W->resid[j] = (akf_real)resid[j] * a->m_inv[j];
    }
    if (skip) {                            /* a held measurement: SKIP_SCALE times its noise */
        for (i = 0; i < M; i++)
            for (j = 0; j < M; j++) W->R_saved[i][j] = a->R[i][j];
        for (j = 0; j < M; j++)
            if ((skip >> j) & 1) a->R[j][j] *= SKIP_SCALE;
    }
    adaptive = AKF_ADAPTIVE && (flags & AKF_COV_ADAPT) && !skip;
    a->guard_hits += gain(a, adaptive);
    if (skip)
        for (i = 0; i < M; i++)
            for (j = 0; j < M; j++) a->R[i][j] = W->R_saved[i][j];
    for (i = 0; i < N * M; i++) {          /* quantize_gain */
        akf_real v = a->K[i / M][i % M];
        int32_t q = isfinite(v) ? to_fixed(v, a->k_scale[i]) : 0;
        if (q == INT32_MAX || q == INT32_MIN) a->saturations++;
        a->k_q[i] = q;
    }
    for (i = 0; i < N; i++)
        for (j = 0; j < N; j++)
            if (!isfinite(a->P[i][j])) return 0;
    return 1;
}

void fx_tick_cov(fx_state_t *s, akf_cov_t *a, const akf_in_t *in)
{
    int finite;
    fx_measure(s, in->counts);
    finite = akf_cov_step(a, in->q_road, in->flags, s->resid);
    fx_correct(s, a->k_q, a->r_q);
    if (!finite || (in->flags & AKF_COV_RESTART)) {
        int i;
        for (i = 0; i < 5; i++) s->x[i] = 0;
        akf_cov_init(a);
    }
    fx_control(s, in->want, in->passive, in->fault, in->regen);
}
