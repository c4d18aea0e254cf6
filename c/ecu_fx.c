/* See ecu_fx.h. Each function mirrors the one of the same name in firmware/fx/path.py
 * (the table in firmware/fx/__init__.py). */
#include "ecu_fx.h"

#include <string.h>

#define INT32_MAX_ 2147483647LL
#define INT32_MIN_ (-2147483647LL - 1)

static int32_t sat32(int64_t x)
{
    return (int32_t)(x > INT32_MAX_ ? INT32_MAX_ : x < INT32_MIN_ ? INT32_MIN_ : x);
}

static int16_t sat16(int64_t x)
{
    return (int16_t)(x > 32767 ? 32767 : x < -32768 ? -32768 : x);
}

/* p / 2^s, rounded half away from zero; |p| <= 2^62, s in [0, 62] */
static int64_t rshift_round(int64_t p, int s)
{
    int64_t half;
    if (s == 0) {
        return p;
    }
    half = (int64_t)1 << (s - 1);
    return p >= 0 ? (p + half) >> s : -((half - p) >> s);
}

static int32_t mul(int32_t a, int32_t b, int s)
{
    return sat32(rshift_round((int64_t)a * (int64_t)b, s));
}

static int32_t add(int32_t a, int32_t b) { return sat32((int64_t)a + b); }
static int32_t sub(int32_t a, int32_t b) { return sat32((int64_t)a - b); }
static int32_t neg(int32_t a) { return sat32(-(int64_t)a); }

static int32_t clamp(int32_t x, int32_t lo, int32_t hi)
{
    return x < lo ? lo : x > hi ? hi : x;
}

static int64_t div_round(int64_t a, int64_t n)
{
    int64_t q = ((a < 0 ? -a : a) + n / 2) / n;
    return a >= 0 ? q : -q;
}

static int same_sign_or_zero(int32_t a, int32_t b)
{
    return a == 0 || b == 0 || ((a > 0) == (b > 0));
}

/* constant c (mantissa m, frac f) times x from format f_in to f_out */
#define CM(name, x, f_in, f_out) mul(name##_Q31, (x), name##_Q31_FRAC + (f_in) - (f_out))
#define AM(name, i, x, f_in, f_out) \
    mul(name##_Q31[i], (x), name##_Q31_FRAC[i] + (f_in) - (f_out))

#define ONE_NN ((int32_t)1 << FX_F_NN)

void fx_init(fx_state_t *s)
{
    int i;
    memset(s, 0, sizeof *s);
    s->ctrl = FX_CONTROLLERS[MODES_INITIAL_MODE];
    s->ctrl_from = CTRL_NONE;
    for (i = 0; i < 20; i++) s->w_h[i] = FX_BP_W_HIDDEN_Q31[i];
    for (i = 0; i < 5; i++) s->b_h[i] = FX_BP_B_HIDDEN_Q31[i];
    for (i = 0; i < 15; i++) s->w_o[i] = FX_BP_W_OUT_Q31[i];
    for (i = 0; i < 3; i++) s->b_o[i] = FX_BP_B_OUT_Q31[i];
    s->bp_fresh = 1;
}

/* ------------------------------------------------------------------ 1. measure */

static int32_t adc_signal(int k, int32_t counts)
{
    if (counts < 0) {
        return 0;
    }
    return add(FX_ADC_OFF_Q31[k], AM(FX_ADC_LSB, k, counts, 0, FX_ADC_FRAC[k]));
}

/* the bump stops' force on the body at the stroke defl (0 without bump stops) */
static int32_t bump_force(int32_t defl)
{
    if (FX_BUMP_K_Q31 == 0) {
        return 0;
    }
    if (defl > FX_BUMP_CLEAR_Q31) {
        return neg(CM(FX_BUMP_K, sub(defl, FX_BUMP_CLEAR_Q31), FX_F_POS, FX_F_FORCE));
    }
    if (defl < -FX_BUMP_CLEAR_Q31) {
        return neg(CM(FX_BUMP_K, add(defl, FX_BUMP_CLEAR_Q31), FX_F_POS, FX_F_FORCE));
    }
    return 0;
}

void fx_measure(fx_state_t *s, const int32_t counts[4])
{
    int i, j;
    int32_t rel_prev, known, u, z[3];
    int32_t xp[5];
    s->ba = adc_signal(0, counts[0]);
    s->wa = adc_signal(1, counts[1]);
    s->defl = adc_signal(2, counts[2]);
    s->cur = adc_signal(3, counts[3]);
    rel_prev = sub(s->x[0], s->x[1]);
    if (same_sign_or_zero(s->cur, rel_prev)) {
        s->force_meas = CM(FX_KF_ETA, s->cur, FX_F_CUR, FX_F_FORCE);
    } else {
        s->force_meas = CM(FX_KF_OVER_ETA, s->cur, FX_F_CUR, FX_F_FORCE);
    }
    known = add(s->force_meas, bump_force(s->defl));     /* the actuator's and the bump stops' */
    u = sat32(rshift_round((int64_t)s->force_known_prev + known, 1));
    s->force_known_prev = known;
    for (i = 0; i < 5; i++) {
        int64_t acc = AM(FX_GAMMA, i, u, FX_F_FORCE, FX_STATE_FRAC[i]);
        for (j = 0; j < 5; j++) {
            acc += AM(FX_PHI, 5 * i + j, s->x[j], FX_STATE_FRAC[j], FX_STATE_FRAC[i]);
        }
        xp[i] = sat32(acc);
    }
    for (i = 0; i < 5; i++) {
        s->x[i] = xp[i];
    }
    z[0] = s->ba;
    z[1] = s->defl;
    z[2] = s->wa;
    for (i = 0; i < FX_N_MEAS; i++) {
        int64_t acc = (int64_t)z[i] - AM(FX_D, i, known, FX_F_FORCE, FX_MEAS_FRAC[i]);
        for (j = 0; j < 5; j++) {
            acc -= AM(FX_H, 5 * i + j, xp[j], FX_STATE_FRAC[j], FX_MEAS_FRAC[i]);
        }
        s->resid[i] = sat32(acc);
    }
}

/* ------------------------------------------------------------------ 3. correct */

void fx_correct(fx_state_t *s, const int32_t *k, const int32_t *r)
{
    int i, j;
    int32_t eps[FX_N_MEAS];
    for (j = 0; j < FX_N_MEAS; j++) {
        eps[j] = FX_BIAS_ADAPTIVE ? sub(s->resid[j], r[j]) : s->resid[j];
    }
    for (i = 0; i < 5; i++) {
        int64_t acc = s->x[i];
        for (j = 0; j < FX_N_MEAS; j++) {
            int n = FX_N_MEAS * i + j;
            acc += mul(k[n], eps[j], FX_K_Q31_FRAC[n] + FX_MEAS_FRAC[j] - FX_STATE_FRAC[i]);
        }
        s->x[i] = sat32(acc);
    }
}

/* ------------------------------------------------------------------ 5. control */

static int32_t tanh_q(int32_t v)
{
    const int sh = FX_F_NN - FX_TANH_STEP_BITS;
    int64_t a = v < 0 ? -(int64_t)v : (int64_t)v;
    int64_t idx = a >> sh;
    int64_t t;
    if (idx >= FX_TANH_N) {
        t = FX_TANH_LUT_Q31[FX_TANH_N];
    } else {
        int64_t lo = FX_TANH_LUT_Q31[idx], hi = FX_TANH_LUT_Q31[idx + 1];
        t = lo + rshift_round((hi - lo) * (a & (((int64_t)1 << sh) - 1)), sh);
    }
    t = rshift_round(t, FX_F_TANH - FX_F_NN);
    return (int32_t)(v < 0 ? -t : t);
}

/* returns u; tp, ti, td: the increments du/dK */
static int32_t pid_step(fx_pid_t *st, int32_t e, int32_t kp, int32_t ki, int32_t kd,
                        int32_t *tp, int32_t *ti, int32_t *td)
{
    int64_t u;
    *tp = sub(e, st->e1);
    *ti = CM(FX_DT, e, FX_F_ACC, FX_F_VEL);
    *td = CM(FX_INV_DT, sat32((int64_t)e - 2 * (int64_t)st->e1 + st->e2), FX_F_ACC, FX_F_JERK);
    u = (int64_t)CM(FX_PID_LEAK, st->u, FX_F_FORCE, FX_F_FORCE)
        + mul(kp, *tp, FX_F_KP + FX_F_ACC - FX_F_FORCE)
        + mul(ki, *ti, FX_F_KI + FX_F_VEL - FX_F_FORCE)
        + mul(kd, *td, FX_F_KD + FX_F_JERK - FX_F_FORCE);
    st->u = clamp(sat32(u), -FX_FORCE_LIMIT_Q31, FX_FORCE_LIMIT_Q31);
    st->e2 = st->e1;
    st->e1 = e;
    return st->u;
}

/* gradient step with momentum of one layer (row-major weights, one row per delta) */
static void learn_layer(int32_t *w, int32_t *dw, int32_t *b, int32_t *db, const int32_t *delta,
                        int n_out, const int32_t *in, int n_in)
{
    int r, j;
    for (r = 0; r < n_out; r++) {
        int32_t ed = CM(FX_BP_ETA, delta[r], FX_F_W, FX_F_W);
        for (j = 0; j < n_in; j++) {
            int n = n_in * r + j;
            dw[n] = add(CM(FX_BP_ALPHA, dw[n], FX_F_W, FX_F_W), mul(ed, in[j], FX_F_NN));
            w[n] = add(w[n], dw[n]);
        }
        db[r] = add(CM(FX_BP_ALPHA, db[r], FX_F_W, FX_F_W), ed);
        b[r] = add(b[r], db[r]);
    }
}

static int32_t bppid_step(fx_state_t *s)
{
    static const int gf[3] = {FX_F_KP, FX_F_KI, FX_F_KD};
    static const int du_f[3] = {FX_F_ACC, FX_F_VEL, FX_F_JERK};
    int i, j, k;
    int32_t y, e, u, xin[4], h[5], g[3], du[3], d_o[3], d_h[5];
    y = CM(FX_BP_INV_INPUT_SCALE, s->ba, FX_F_ACC, FX_F_NN);
    e = neg(y);
    xin[0] = 0;
    xin[1] = y;
    xin[2] = e;
    xin[3] = ONE_NN;
    for (i = 0; i < 5; i++) {
        int64_t acc = rshift_round(s->b_h[i], FX_F_W - FX_F_NN);
        for (j = 0; j < 4; j++) {
            acc += mul(s->w_h[4 * i + j], xin[j], FX_F_W);
        }
        h[i] = tanh_q(sat32(acc));
    }
    for (k = 0; k < 3; k++) {
        int64_t acc = rshift_round(s->b_o[k], FX_F_W - FX_F_NN);
        for (i = 0; i < 5; i++) {
            acc += mul(s->w_o[5 * k + i], h[i], FX_F_W);
        }
        g[k] = sat32(rshift_round((int64_t)ONE_NN + tanh_q(sat32(acc)), 1));
    }
    for (k = 0; k < 3; k++) {
        s->gains[k] = AM(FX_BP_SCALE, k, g[k], FX_F_NN, gf[k]);
        /* the PID's gains: the network's, low-passed (firmware/control.py) */
        s->k_pid[k] = s->bp_fresh ? s->gains[k]
                    : add(s->k_pid[k], CM(FX_BP_GAIN_ALPHA, sub(s->gains[k], s->k_pid[k]),
                                          gf[k], gf[k]));
    }
    s->bp_fresh = 0;
    u = pid_step(&s->bp_pid, neg(s->ba), s->k_pid[0], s->k_pid[1], s->k_pid[2],
                 &du[0], &du[1], &du[2]);
    /* learning */
    for (k = 0; k < 3; k++) {
        int32_t a_k = AM(FX_BP_DU_SCALE, k, du[k], du_f[k], FX_F_NN);
        int32_t gp = mul(g[k], ONE_NN - g[k], FX_F_NN - 1);
        d_o[k] = mul(mul(e, a_k, FX_F_NN), gp, 2 * FX_F_NN - FX_F_W);
    }
    for (i = 0; i < 5; i++) {
        int64_t back = 0;
        int32_t one_m_h2;
        for (k = 0; k < 3; k++) {
            back += mul(s->w_o[5 * k + i], d_o[k], FX_F_W);
        }
        one_m_h2 = ONE_NN - mul(h[i], h[i], FX_F_NN);
        d_h[i] = mul(one_m_h2, sat32(back), FX_F_NN);
    }
    learn_layer(s->w_o, s->dw_o, s->b_o, s->db_o, d_o, 3, h, 5);
    learn_layer(s->w_h, s->dw_h, s->b_h, s->db_h, d_h, 5, xin, 4);
    return u;
}

static int32_t dot_state(const int32_t *m, const int8_t *frac, const int32_t *x)
{
    int64_t acc = 0;
    int j;
    for (j = 0; j < 5; j++) {
        acc += mul(m[j], x[j], frac[j] + FX_STATE_FRAC[j] - FX_F_FORCE);
    }
    return sat32(acc);
}

static int32_t lqr_force(const int32_t *m, const int8_t *frac, const int32_t *x)
{
    return neg(dot_state(m, frac, x));
}

static int32_t skyhook_force(const int32_t *x)
{
    return neg(sat32((int64_t)CM(FX_SKYHOOK_C, x[0], FX_F_VEL, FX_F_FORCE)
                     + CM(FX_SKYHOOK_PASSIVE_C, sub(x[0], x[1]), FX_F_VEL, FX_F_FORCE)));
}

static int32_t regen_force(const int32_t *x)
{
    int32_t rel = sub(x[0], x[1]);
    int32_t f = neg(sat32((int64_t)CM(FX_REGEN_C, rel, FX_F_VEL, FX_F_FORCE)
                          + CM(FX_REGEN_SKYHOOK_C, x[0], FX_F_VEL, FX_F_FORCE)));
    return ((f > 0 && rel > 0) || (f < 0 && rel < 0)) ? 0 : f;
}

static int32_t force_of(fx_state_t *s, int ctrl)
{
    int32_t tp, ti, td;
    switch (ctrl) {
    case CTRL_LQR:
        return lqr_force(FX_K_SAFETY_Q31, FX_K_SAFETY_Q31_FRAC, s->x);
    case CTRL_GALQR:
        return lqr_force(FX_K_COMPREHENSIVE_Q31, FX_K_COMPREHENSIVE_Q31_FRAC, s->x);
    case CTRL_SKYHOOK:
        return skyhook_force(s->x);
    case CTRL_PID:
        return pid_step(&s->pid, neg(s->ba), FX_PID_KP_Q31, FX_PID_KI_Q31, FX_PID_KD_Q31,
                        &tp, &ti, &td);
    case CTRL_BPPID: {         /* the network's PID, then the state feedback under it */
        int32_t u = bppid_step(s);
        return add(u, lqr_force(FX_K_COMFORT_Q31, FX_K_COMFORT_Q31_FRAC, s->x));
    }
    case CTRL_REGEN:
        return regen_force(s->x);
    default:
        return 0;
    }
}

static int32_t current_reference(int32_t force, int32_t rel, int compensate)
{
    int32_t demand = compensate ? add(force, CM(FX_FRICTION, rel, FX_F_VEL, FX_F_FORCE)) : force;
    int32_t i_ref;
    if (same_sign_or_zero(demand, rel)) {
        i_ref = CM(FX_INV_ETA_KF, demand, FX_F_FORCE, FX_F_CUR);
    } else {
        i_ref = CM(FX_ETA_OVER_KF, demand, FX_F_FORCE, FX_F_CUR);
    }
    return clamp(i_ref, -FX_CURRENT_LIMIT_Q31, FX_CURRENT_LIMIT_Q31);
}

static int16_t actuator_step(fx_state_t *s, int32_t i_ref, int32_t rel, int regen, int32_t rel_acc)
{
    int32_t i_meas = s->cur, emf, v_dc, per_v_m, v_ff, v, lo, hi;
    int per_v_frac, saturated;
    int16_t duty;
    if (s->observer_valid) {
        emf = sub(s->voltage, CM(FX_INV_CUR_B, sub(i_meas, CM(FX_CUR_A, s->i_prev, FX_F_CUR, FX_F_CUR)),
                                 FX_F_CUR, FX_F_VOLT));
        emf = add(emf, CM(FX_KF_DT, rel_acc, FX_F_ACC, FX_F_VOLT));
    } else {
        emf = CM(FX_KF, add(rel, CM(FX_HALF_DT, rel_acc, FX_F_ACC, FX_F_VEL)), FX_F_VEL, FX_F_VOLT);
    }
    if (regen) {
        v_dc = FX_V_STORAGE_Q31;
        per_v_m = FX_DUTY_PER_V_STORAGE_Q31;
        per_v_frac = FX_DUTY_PER_V_STORAGE_Q31_FRAC;
    } else {
        v_dc = FX_V_BUS_Q31;
        per_v_m = FX_DUTY_PER_V_BUS_Q31;
        per_v_frac = FX_DUTY_PER_V_BUS_Q31_FRAC;
    }
    v_ff = add(emf, CM(FX_INV_CUR_B, sub(i_ref, CM(FX_CUR_A, i_meas, FX_F_CUR, FX_F_CUR)),
                       FX_F_CUR, FX_F_VOLT));
    v = add(v_ff, s->integ);
    lo = -v_dc;
    hi = v_dc;
    if (regen) {
        int32_t r = CM(FX_REGEN_MIN_RATIO, emf, FX_F_VOLT, FX_F_VOLT);
        int32_t a = r <= emf ? r : emf, b = r <= emf ? emf : r;
        lo = lo > a ? lo : a;
        hi = hi < b ? hi : b;
    }
    saturated = v < lo || v > hi;
    v = v > lo ? v : lo;
    v = v < hi ? v : hi;
    if (!saturated) {
        s->integ = clamp(add(s->integ, CM(FX_CUR_KI, sub(s->i_ref_prev, i_meas), FX_F_CUR, FX_F_VOLT)),
                         -FX_INTEG_LIMIT_Q31, FX_INTEG_LIMIT_Q31);
    }
    s->i_ref_prev = i_ref;
    duty = sat16(rshift_round((int64_t)v * per_v_m, per_v_frac + FX_F_VOLT));
    s->voltage = sat32(rshift_round((int64_t)duty * v_dc, 15));
    s->i_prev = i_meas;
    s->observer_valid = 1;
    return duty;
}

static void actuator_reset(fx_state_t *s)
{
    s->integ = 0;
    s->i_ref_prev = 0;
    s->voltage = 0;
    s->observer_valid = 0;
}

int16_t fx_control(fx_state_t *s, int want, int passive, int fault, int regen)
{
    const int n = FX_RAMP_TICKS;
    int32_t force;
    int16_t duty;
    int active;
    if (want != s->ctrl) {
        s->ctrl_from = s->ctrl;
        s->ctrl = want;
        s->ramp = 0;
        if (want == CTRL_PID) {
            s->pid.u = 0;
        } else if (want == CTRL_BPPID) {
            s->bp_pid.u = 0;
            s->bp_fresh = 1;
        }
    }
    force = force_of(s, s->ctrl);
    if (s->ramp < n) {
        int32_t f_from;
        s->ramp += 1;
        f_from = force_of(s, s->ctrl_from);
        force = sat32(div_round((int64_t)s->ramp * force + (int64_t)(n - s->ramp) * f_from, n));
    }
    force = clamp(force, -FX_FORCE_LIMIT_Q31, FX_FORCE_LIMIT_Q31);
    active = (!passive || s->ramp < n) && !fault;
    if (active) {
        int32_t rel = sub(s->x[0], s->x[1]);
        int32_t i_ref = current_reference(force, rel, !regen);
        int32_t rel_acc = add(sub(s->ba, s->wa),
                              CM(FX_INV_MASS, sub(force, s->force_meas), FX_F_FORCE, FX_F_ACC));
        duty = actuator_step(s, i_ref, rel, regen, rel_acc);
    } else {
        actuator_reset(s);
        duty = 0;
        force = 0;
    }
    s->force = force;
    s->duty = duty;
    return duty;
}

void fx_tick(fx_state_t *s, const fx_in_t *in)
{
    fx_measure(s, in->counts);
    fx_correct(s, in->k, in->r);
    if (in->reset) {
        int i;
        for (i = 0; i < 5; i++) {
            s->x[i] = 0;
        }
    }
    fx_control(s, in->want, in->passive, in->fault, in->regen);
}
