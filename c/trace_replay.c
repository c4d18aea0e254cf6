/* Replays a recorded trace through the C fixed-point path (tests/test_c_parity.py).
 * stdin, one tick per line: counts[4] (-1: none) k[5*FX_N_MEAS] r[FX_N_MEAS] want passive
 * fault regen reset. stdout, one line per tick: duty force x[5] resid[FX_N_MEAS] integ voltage.
 * Exit 2 on a malformed line. */
#include <stdio.h>

#include "ecu_fx.h"

static int read_int(long *v)
{
    return scanf("%ld", v) == 1;
}

int main(void)
{
    fx_state_t s;
    fx_in_t in;
    long v;
    long ticks = 0;
    int i;
    fx_init(&s);
    while (read_int(&v)) {
        int ok = 1;
        in.counts[0] = (int32_t)v;
        for (i = 1; i < 4 && ok; i++) ok = read_int(&v), in.counts[i] = (int32_t)v;
        for (i = 0; i < 5 * FX_N_MEAS && ok; i++) ok = read_int(&v), in.k[i] = (int32_t)v;
        for (i = 0; i < FX_N_MEAS && ok; i++) ok = read_int(&v), in.r[i] = (int32_t)v;
        ok = ok && read_int(&v);
        in.want = (int)v;
        ok = ok && read_int(&v);
        in.passive = (int)v;
        ok = ok && read_int(&v);
        in.fault = (int)v;
        ok = ok && read_int(&v);
        in.regen = (int)v;
        ok = ok && read_int(&v);
        in.reset = (int)v;
        if (!ok) {
            fprintf(stderr, "trace_replay: malformed tick %ld\n", ticks);
            return 2;
        }
        fx_tick(&s, &in);
        printf("%d %ld", (int)s.duty, (long)s.force);
        for (i = 0; i < 5; i++) printf(" %ld", (long)s.x[i]);
        for (i = 0; i < FX_N_MEAS; i++) printf(" %ld", (long)s.resid[i]);
        printf(" %ld %ld\n", (long)s.integ, (long)s.voltage);
        ticks++;
    }
    return 0;
}
