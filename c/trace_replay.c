/* Replays a recorded trace through the C fixed-point path (tests/test_c_parity.py).
 * stdin, one tick per line: counts[4] (-1: none) k[5*FX_N_MEAS] r[FX_N_MEAS] want passive
 * fault regen reset. stdout, one line per tick: duty force x[5] resid[FX_N_MEAS] integ voltage.
 * Exit 2 on a malformed line.
 *
 * `trace_replay --cov`: the same with the covariance side of the filter in C (akf_cov.c;
 * built with -DAKF_FLOAT, in float32). stdin, one tick per line: counts[4] q_road flags want
 * passive fault regen (q_road a C99 hex float, flags the AKF_COV_* bits). stdout: the line
 * above, then k[5*FX_N_MEAS] r[FX_N_MEAS] (the Q numbers handed to fx_correct) and the float
 * gain K[5*FX_N_MEAS] row-major as hex floats (%a, widened to double).
 *
 * `trace_replay --bench R` (make bench's c_core_tick_us): reads the whole trace first, then
 * runs fx_init and fx_tick over it R times, each run timed alone (CLOCK_MONOTONIC); prints
 * "ticks N best_ns_per_tick B median_ns_per_tick M checksum C", the checksum folding every
 * tick's duty and force so that the work cannot be optimised away. Exit 2 on bad arguments. */
#define _POSIX_C_SOURCE 199309L
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>

#include "akf_cov.h"
#include "ecu_fx.h"

static int read_int(long *v)
{
    return scanf("%ld", v) == 1;
}

/* A tick line's controller and mode flags (want passive fault regen): 1 read, 0 not. */
static int read_mode(int *want, int *passive, int *fault, int *regen)
{
    long v[4];
    int i;
    for (i = 0; i < 4; i++) {
        if (!read_int(&v[i])) return 0;
    }
    *want = (int)v[0], *passive = (int)v[1], *fault = (int)v[2], *regen = (int)v[3];
    return 1;
}

/* One tick's line into *in: 1 read, 0 end of input, -1 malformed. */
static int read_tick(fx_in_t *in)
{
    long v;
    int i, ok = 1;
    if (!read_int(&v)) {
        return 0;
    }
    in->counts[0] = (int32_t)v;
    for (i = 1; i < 4 && ok; i++) ok = read_int(&v), in->counts[i] = (int32_t)v;
    for (i = 0; i < 5 * FX_N_MEAS && ok; i++) ok = read_int(&v), in->k[i] = (int32_t)v;
    for (i = 0; i < FX_N_MEAS && ok; i++) ok = read_int(&v), in->r[i] = (int32_t)v;
    ok = ok && read_mode(&in->want, &in->passive, &in->fault, &in->regen);
    ok = ok && read_int(&v);
    in->reset = (int)v;
    return ok ? 1 : -1;
}

static void print_outputs(const fx_state_t *s)
{
    int i;
    printf("%d %ld", (int)s->duty, (long)s->force);
    for (i = 0; i < 5; i++) printf(" %ld", (long)s->x[i]);
    for (i = 0; i < FX_N_MEAS; i++) printf(" %ld", (long)s->resid[i]);
    printf(" %ld %ld", (long)s->integ, (long)s->voltage);
}

static int replay(void)
{
    fx_state_t s;
    fx_in_t in;
    long ticks = 0;
    int r;
    fx_init(&s);
    while ((r = read_tick(&in)) == 1) {
        fx_tick(&s, &in);
        print_outputs(&s);
        printf("\n");
        ticks++;
    }
    if (r < 0) {
        fprintf(stderr, "trace_replay: malformed tick %ld\n", ticks);
        return 2;
    }
    return 0;
}

/* One --cov tick's line into *in: 1 read, 0 end of input, -1 malformed. */
static int read_cov_tick(akf_in_t *in)
{
    long v;
    double q;
    int i, ok = 1;
    if (!read_int(&v)) {
        return 0;
    }
    in->counts[0] = (int32_t)v;
    for (i = 1; i < 4 && ok; i++) ok = read_int(&v), in->counts[i] = (int32_t)v;
    ok = ok && scanf("%lf", &q) == 1;
    in->q_road = (akf_real)q;
    ok = ok && read_int(&v);
    in->flags = (int)v;
    ok = ok && read_mode(&in->want, &in->passive, &in->fault, &in->regen);
    return ok ? 1 : -1;
}

static int replay_cov(void)
{
    static akf_cov_t a;           /* (zeroed: the saturation count starts at 0) */
    fx_state_t s;
    akf_in_t in;
    long ticks = 0;
    int i, r;
    fx_init(&s);
    akf_cov_init(&a);
    while ((r = read_cov_tick(&in)) == 1) {
        fx_tick_cov(&s, &a, &in);
        print_outputs(&s);
        for (i = 0; i < 5 * FX_N_MEAS; i++) printf(" %ld", (long)a.k_q[i]);
        for (i = 0; i < FX_N_MEAS; i++) printf(" %ld", (long)a.r_q[i]);
        for (i = 0; i < 5 * FX_N_MEAS; i++) {
            printf(" %a", (double)a.K[i / FX_N_MEAS][i % FX_N_MEAS]);
        }
        printf("\n");
        ticks++;
    }
    if (r < 0) {
        fprintf(stderr, "trace_replay: malformed tick %ld\n", ticks);
        return 2;
    }
    return 0;
}

static double now_ns(void)
{
    struct timespec t;
    clock_gettime(CLOCK_MONOTONIC, &t);
    return (double)t.tv_sec * 1e9 + (double)t.tv_nsec;
}

static int cmp_double(const void *a, const void *b)
{
    double x = *(const double *)a, y = *(const double *)b;
    return (x > y) - (x < y);
}

static int bench(long repeats)
{
    fx_state_t s;
    fx_in_t *trace = NULL;
    double *per_tick;
    long n = 0, cap = 0, k, rep;
    unsigned long checksum = 0;
    int r;
    for (;;) {
        if (n == cap) {
            fx_in_t *grown;
            cap = cap ? 2 * cap : 4096;
            grown = realloc(trace, (size_t)cap * sizeof *trace);
            if (!grown) {
                fprintf(stderr, "trace_replay: out of memory at tick %ld\n", n);
                free(trace);
                return 2;
            }
            trace = grown;
        }
        r = read_tick(&trace[n]);
        if (r == 0) break;
        if (r < 0) {
            fprintf(stderr, "trace_replay: malformed tick %ld\n", n);
            free(trace);
            return 2;
        }
        n++;
    }
    if (n == 0) {
        fprintf(stderr, "trace_replay: --bench needs a trace on stdin\n");
        free(trace);
        return 2;
    }
    per_tick = malloc((size_t)repeats * sizeof *per_tick);
    if (!per_tick) {
        free(trace);
        return 2;
    }
    for (rep = 0; rep < repeats; rep++) {
        double t0 = now_ns();
        fx_init(&s);
        for (k = 0; k < n; k++) {
            fx_tick(&s, &trace[k]);
            checksum = checksum * 31u + (unsigned long)(uint16_t)s.duty
                       + (unsigned long)(uint32_t)s.force;
        }
        per_tick[rep] = (now_ns() - t0) / (double)n;
    }
    qsort(per_tick, (size_t)repeats, sizeof *per_tick, cmp_double);
    printf("ticks %ld best_ns_per_tick %.2f median_ns_per_tick %.2f checksum %lu\n", n,
           per_tick[0], per_tick[repeats / 2], checksum);
    free(per_tick);
    free(trace);
    return 0;
}

int main(int argc, char **argv)
{
    if (argc == 1) {
        return replay();
    }
    if (argc == 2 && strcmp(argv[1], "--cov") == 0) {
        return replay_cov();
    }
    if (argc == 3 && strcmp(argv[1], "--bench") == 0) {
        char *end;
        long repeats = strtol(argv[2], &end, 10);
        if (*end == '\0' && repeats > 0 && repeats <= 100000) {
            return bench(repeats);
        }
    }
    fprintf(stderr, "usage: trace_replay [--cov | --bench REPEATS] < trace\n");
    return 2;
}
