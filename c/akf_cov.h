/* The covariance side of the ECU's adaptive Kalman filter in C99: the forces off the model
 * added as process noise, the prediction of P, the Sage-Husa R-hat with its forgetting factor
 * and guard (symmetrised, eigenvalues within [floor, R_CEILING floor]), the gain and the
 * Joseph-form update. It is firmware/kernels/akf.py (gain_ws, guard_ws, psd_shifted,
 * jacobi_into, solve_into, predict_ws) and firmware/fx/estimate.py operation for operation,
 * in the same order: built in double with -ffp-contract=off it gives the Python path's bits
 * (tests/test_c_parity.py, make pil on the Cortex-M7). Built with -DAKF_FLOAT it runs in
 * float32, what a Cortex-M4F's single-precision FPU affords (its deviation: docs/pil.md).
 *
 * With it the fixed-point tick needs nothing from a float estimator: fx_tick_cov takes the
 * ADC counts, the road's process-noise intensity and the flags the supervisor decides
 * (AKF_COV_* in the tables: the measurements held, R-hat may adapt, the forces off the model,
 * a restart) and computes the gain and bias it hands to fx_correct itself. */
#ifndef AKF_COV_H
#define AKF_COV_H

#include <stdint.h>

#include "ecu_fx.h"

#ifdef AKF_FLOAT
typedef float akf_real;
#else
typedef double akf_real;
#endif

#define AKF_M FX_N_MEAS

/* The intermediates of one tick (firmware.kernels.akf.workspace_dtype): kept in the state,
 * off the stack. */
typedef struct {
    akf_real t1[5][5], t2[5][5];
    akf_real resid[AKF_M], eps[AKF_M];
    akf_real HP[AKF_M][5], HPHt[AKF_M][AKF_M], Ra[AKF_M][AKF_M], S[AKF_M][AKF_M];
    akf_real Y[AKF_M][5], KHP[5][5], KS[5][AKF_M], KSKt[5][5], Pj[5][5];
    akf_real Rg[AKF_M][AKF_M], ja[AKF_M][AKF_M], jV[AKF_M][AKF_M], jw[AKF_M];
    akf_real Mx[AKF_M][AKF_M], R_saved[AKF_M][AKF_M];
} akf_ws_t;

typedef struct {
    akf_real P[5][5];             /* the state covariance */
    akf_real R[AKF_M][AKF_M];     /* R-hat */
    akf_real r[AKF_M];            /* r-hat, the measurement bias */
    akf_real b_pow;               /* b^(t+1) */
    akf_real K[5][AKF_M];         /* the last gain */
    int32_t k_q[5 * AKF_M];       /* ... as Q numbers in FX_K_Q31_FRAC */
    int32_t r_q[AKF_M];           /* r-hat before this tick's update, FX_MEAS_FRAC */
    int32_t guard_hits, saturations;
    akf_real k_scale[5 * AKF_M], m_scale[AKF_M], m_inv[AKF_M];  /* 2^frac, 2^-frac */
    akf_ws_t ws;
} akf_cov_t;

/* One tick's inputs with the estimator in C: the ADC counts (-1: none yet), the road's
 * process-noise intensity, the AKF_COV_* flags, the controller of the active mode and the
 * mode flags (fx_in_t without the gain and bias). */
typedef struct {
    int32_t counts[4];
    akf_real q_road;
    int flags;
    int want;
    int passive, fault, regen;
} akf_in_t;

/* power-up (and restart): P = P0, R-hat = R0, r-hat = 0, b^1 */
void akf_cov_init(akf_cov_t *a);
/* the covariance side of one tick from the residual of fx_measure (FX_MEAS_FRAC): fills
 * a->k_q and a->r_q; returns whether P is finite */
int akf_cov_step(akf_cov_t *a, akf_real q_road, int flags, const int32_t resid[AKF_M]);
/* fx_tick with the gain from akf_cov_step; a non-finite P or AKF_COV_RESTART restarts both
 * halves of the filter, as the ECU does */
void fx_tick_cov(fx_state_t *s, akf_cov_t *a, const akf_in_t *in);

#endif /* AKF_COV_H */
