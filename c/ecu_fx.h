/* The fixed-point control path of the ECU in C99: ADC counts -> scaled signals -> state
 * estimate -> controller -> PWM duty counts. Integer arithmetic only; every constant comes from
 * the generated tables (generated/ecu_tables.h, `make tables`). It is firmware/fx/path.py
 * function by function (the table in firmware/fx/__init__.py): the
 * parity test (tests/test_c_parity.py) feeds both the same recorded trace and requires
 * identical integers on every tick. Formats and conventions: firmware/fixedpoint.py. */
#ifndef ECU_FX_H
#define ECU_FX_H

#include <stdint.h>

#include "ecu_tables.h"

typedef struct {
    int32_t e1, e2, u;
} fx_pid_t;

typedef struct {
    int32_t x[5];                 /* [zs', zt', zs, zt, zf] in FX_STATE_FRAC */
    int32_t resid[FX_N_MEAS];     /* z - H x_pred - D u, FX_MEAS_FRAC */
    int32_t ba, wa, defl, cur;    /* signals */
    int32_t force_meas, force_known_prev;
    int ctrl, ctrl_from, ramp;
    fx_pid_t pid, bp_pid;
    int32_t w_h[20], b_h[5], w_o[15], b_o[3];
    int32_t dw_h[20], db_h[5], dw_o[15], db_o[3];
    int32_t gains[3];
    int32_t k_pid[3];             /* the PID's gains: the network's, low-passed */
    int bp_fresh;                 /* seed k_pid with the network's gains at the next step */
    int32_t integ, i_ref_prev, voltage, i_prev;
    int observer_valid;
    int32_t force;
    int16_t duty;
} fx_state_t;

/* One tick's inputs: ADC counts (-1: no good sample yet), the Kalman gain and bias handed over
 * by the float estimator (Q numbers in FX_K_Q31_FRAC / FX_MEAS_FRAC), the controller of the
 * active mode and the mode flags. */
typedef struct {
    int32_t counts[4];            /* body accel, wheel accel, deflection, motor current */
    int32_t k[5 * FX_N_MEAS];
    int32_t r[FX_N_MEAS];
    int want;
    int passive, fault, regen, reset;
} fx_in_t;

void fx_init(fx_state_t *s);
void fx_measure(fx_state_t *s, const int32_t counts[4]);
void fx_correct(fx_state_t *s, const int32_t *k, const int32_t *r);
int16_t fx_control(fx_state_t *s, int want, int passive, int fault, int regen);
void fx_tick(fx_state_t *s, const fx_in_t *in);

#endif /* ECU_FX_H */
