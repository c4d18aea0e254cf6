/* Trace replay on the target (make pil, tools/pil.py): c/trace_replay.c's job on a Cortex-M
 * under QEMU, with the cost of each tick read off the virtual clock.
 *
 * In:  trace.bin, the recorded ticks as little-endian int32 records, the fields of fx_in_t in
 *      order: counts[4] k[5*FX_N_MEAS] r[FX_N_MEAS] want passive fault regen reset.
 * Out: out.bin, one record per tick: duty force x[5] resid[FX_N_MEAS] integ voltage (as
 *      trace_replay prints them), then the SysTick counts the tick took and its class
 *      (bits 0-3: the controller in use after the tick; bit 4: a crossfade tick); then a
 *      trailer: PIL_MAGIC, ticks, the deepest stack fx_tick used (bytes, from the painted
 *      stack), the counts of an empty measurement, sizeof(fx_state_t), sizeof(fx_in_t).
 * Exit code 0, 2 (a file could not be opened or written, a short record) or 3 (a fault).
 *
 * The clock: SysTick on the processor clock, which QEMU's MPS2 boards run at 25 MHz of
 * virtual time; with -icount shift=7 every instruction advances that time by 128 ns, so a
 * SysTick count is 40/128 of an instruction and the host recovers the exact instruction
 * count of a tick (round(counts * 128 / 40) after the empty measurement is subtracted).
 *
 * Built with -DPIL_COV (and -DAKF_FLOAT for float32): the tick is fx_tick_cov, the covariance
 * side of the filter in C (akf_cov.c). In: counts[4], q_road as the bytes of an akf_real in
 * two words (float32: the first), flags want passive fault regen. Out: the outputs above,
 * then k[5*FX_N_MEAS] (the Q gain handed to fx_correct) and the float gain K row-major as the
 * bytes of akf_reals (2 words each in double, 1 in float32), then the counts and the class. */
#include <stdint.h>
#include <string.h>

#include "ecu_fx.h"
#include "semihost.h"
#ifdef PIL_COV
#include "akf_cov.h"
#endif

#define PIL_MAGIC 0x214C4950u   /* "PIL!" */
#define CHUNK 64
#ifdef PIL_COV
#define N_OUT (2 + 5 + FX_N_MEAS + 2 + 5 * FX_N_MEAS + 10 * FX_N_MEAS)
#define N_IN (4 + 2 + 5)
typedef akf_in_t tick_in_t;
#define STATE_BYTES (sizeof(fx_state_t) + sizeof(akf_cov_t))
#else
#define N_OUT (2 + 5 + FX_N_MEAS + 2)
#define N_IN (4 + 5 * FX_N_MEAS + FX_N_MEAS + 5)
typedef fx_in_t tick_in_t;
#define STATE_BYTES sizeof(fx_state_t)
#endif

#define SYST_CSR (*(volatile uint32_t *)0xE000E010u)
#define SYST_RVR (*(volatile uint32_t *)0xE000E014u)
#define SYST_CVR (*(volatile uint32_t *)0xE000E018u)
#define PAINT 0xA5A5A5A5u

extern uint32_t __stack_limit;

static int32_t in_buf[CHUNK][N_IN];
static int32_t out_buf[CHUNK][N_OUT + 2];
static fx_state_t state;
static tick_in_t tick_in;
#ifdef PIL_COV
static akf_cov_t cov;
#endif

static uint32_t now(void)
{
    return SYST_CVR;            /* counts down, 24 bits */
}

static uint32_t elapsed(uint32_t t0, uint32_t t1)
{
    return (t0 - t1) & 0xFFFFFFu;
}

/* the stack below the caller's frame, down to __stack_limit, filled with PAINT */
static void __attribute__((noinline)) paint_stack(void)
{
    volatile uint32_t *p = &__stack_limit;
    uint32_t *sp;
    __asm volatile("mov %0, sp" : "=r"(sp));
    while (p < (volatile uint32_t *)sp - 16) *p++ = PAINT;
}

static uint32_t lowest_touched(void)
{
    const uint32_t *p = &__stack_limit;
    while (*p == PAINT) p++;
    return (uint32_t)p;
}

#ifdef PIL_COV
static void unpack(const int32_t *w, akf_in_t *in)
{
    int i;
    for (i = 0; i < 4; i++) in->counts[i] = *w++;
    memcpy(&in->q_road, w, sizeof in->q_road);
    w += 2;
    in->flags = *w++;
    in->want = *w++;
    in->passive = *w++;
    in->fault = *w++;
    in->regen = *w;
}
#else
static void unpack(const int32_t *w, fx_in_t *in)
{
    int i;
    for (i = 0; i < 4; i++) in->counts[i] = *w++;
    for (i = 0; i < 5 * FX_N_MEAS; i++) in->k[i] = *w++;
    for (i = 0; i < FX_N_MEAS; i++) in->r[i] = *w++;
    in->want = *w++;
    in->passive = *w++;
    in->fault = *w++;
    in->regen = *w++;
    in->reset = *w;
}
#endif

static void pack(const fx_state_t *s, int32_t *w)
{
    int i;
    *w++ = s->duty;
    *w++ = s->force;
    for (i = 0; i < 5; i++) *w++ = s->x[i];
    for (i = 0; i < FX_N_MEAS; i++) *w++ = s->resid[i];
    *w++ = s->integ;
    *w++ = s->voltage;
#ifdef PIL_COV
    for (i = 0; i < 5 * FX_N_MEAS; i++) *w++ = cov.k_q[i];
    memset(w, 0, 10 * FX_N_MEAS * sizeof *w);
    memcpy(w, cov.K, sizeof cov.K);
#endif
}

int main(void)
{
    static const char in_name[] = "trace.bin", out_name[] = "out.bin";
    int32_t fin, fout;
    uint32_t ticks = 0, empty, t0, t1, sp_at_call, trailer[6];
    paint_stack();
    SYST_RVR = 0xFFFFFFu;
    SYST_CVR = 0;
    SYST_CSR = 5;                 /* enabled, processor clock, no interrupt */
    fin = sh_open(in_name, sizeof in_name - 1, 1);
    fout = sh_open(out_name, sizeof out_name - 1, 5);
    if (fin < 0 || fout < 0) {
        return 2;
    }
    t0 = now();
    t1 = now();
    empty = elapsed(t0, t1);
    fx_init(&state);
#ifdef PIL_COV
    akf_cov_init(&cov);
#endif
    __asm volatile("mov %0, sp" : "=r"(sp_at_call));
    for (;;) {
        int32_t left = sh_read(fin, in_buf, sizeof in_buf);
        int n = (int)((sizeof in_buf - (uint32_t)left) / sizeof in_buf[0]), k;
        if (left < 0 || (sizeof in_buf - (uint32_t)left) % sizeof in_buf[0] != 0) {
            return 2;
        }
        for (k = 0; k < n; k++) {
            int xf;
            unpack(in_buf[k], &tick_in);
            xf = tick_in.want != state.ctrl || state.ramp < FX_RAMP_TICKS;
            t0 = now();
#ifdef PIL_COV
            fx_tick_cov(&state, &cov, &tick_in);
#else
            fx_tick(&state, &tick_in);
#endif
            t1 = now();
            pack(&state, out_buf[k]);
            out_buf[k][N_OUT] = (int32_t)elapsed(t0, t1);
            out_buf[k][N_OUT + 1] = (state.ctrl & 15) | (xf << 4);
        }
        ticks += (uint32_t)n;
        if (n && sh_write(fout, out_buf, (uint32_t)n * sizeof out_buf[0]) != 0) {
            return 2;
        }
        if (n < CHUNK) {
            break;
        }
    }
    trailer[0] = PIL_MAGIC;
    trailer[1] = ticks;
    trailer[2] = sp_at_call - lowest_touched();
    trailer[3] = empty;
    trailer[4] = STATE_BYTES;
    trailer[5] = sizeof(tick_in_t);
    if (sh_write(fout, trailer, sizeof trailer) != 0) {
        return 2;
    }
    sh_close(fout);
    sh_close(fin);
    return 0;
}
