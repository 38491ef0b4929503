/*
 * Instructions per call of the generated controller on a bare-metal Cortex-M, counted
 * under QEMU's `-icount shift=0`, and the stack its calls use.
 *
 * With -icount shift=0 QEMU advances the virtual clock by exactly 1 ns per guest
 * instruction, so a timer of the board counts instructions, not time: SysTick, clocked
 * from the core clock (25 MHz on the MPS2 boards), ticks once per 40 instructions. The
 * ratio is measured, not assumed: a loop of a known number of instructions is timed
 * first. These are instruction counts (repeatable, the same on every run), not cycles:
 * QEMU models no pipeline, cache, wait state or the FPU's and divider's latencies.
 *
 * Built like loop.c (-DNAME, -DUNAME, -DREAL, -DRATE, -DSTEPS, -DSUBSTEPS) and
 * -DCALLS=<n>. An example with references measured at run time ([references]) is built
 * with -DREFS and the include path of a "refs.h" that defines the jets every call takes:
 * refs_half[<NAME>_N_REFERENCE_JET] (at t = 0.5, for control) and
 * refs_steps[STEPS][<NAME>_N_REFERENCE_JET] (at each step's time).
 * Prints, one record a line (decimal integers):
 *   calibrate <iterations of a 2-instruction loop> <ticks>
 *   control <calls> <ticks>
 *   step <steps> <ticks>          the steps of a closed loop, replayed and timed together
 *   stack <bytes>                 the deepest stack of init, steps and control calls
 *   end
 */
#include "counting.h"

#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)
#define STR_(a) #a
#define STR(a) STR_(a)
#include STR(NAME.h)

#define FN(suffix) CAT(NAME, suffix)
#define CONST(suffix) CAT(UNAME, suffix)
#define NX CONST(_N_PLANT_STATES)
#define NU CONST(_N_INPUTS)
#define NS CONST(_N_STATES)

/* The references' jets, one more argument of control, controller_init and
 * controller_step (docs/references.md); nothing at all without references. */
#ifdef REFS
#include "refs.h"
#define REFS_HALF refs_half,
#define REFS_STEP(k) refs_steps[k],
#define REFS_INIT , refs_steps[0]
#else
#define REFS_HALF
#define REFS_STEP(k)
#define REFS_INIT
#endif

int harness_plant(double t, const double *x, const double *u, const double *params, double *out);

static int rk4(double t, double h, double *x, const double *u)
{
    double k1[NX], k2[NX], k3[NX], k4[NX], tmp[NX];
    int i, status;
    status = harness_plant(t, x, u, NULL, k1);
    for (i = 0; i < NX; ++i) tmp[i] = x[i] + 0.5 * h * k1[i];
    status |= harness_plant(t + 0.5 * h, tmp, u, NULL, k2);
    for (i = 0; i < NX; ++i) tmp[i] = x[i] + 0.5 * h * k2[i];
    status |= harness_plant(t + 0.5 * h, tmp, u, NULL, k3);
    for (i = 0; i < NX; ++i) tmp[i] = x[i] + h * k3[i];
    status |= harness_plant(t + h, tmp, u, NULL, k4);
    for (i = 0; i < NX; ++i) x[i] += h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i]);
    return status;
}

static REAL xs[STEPS][NX];
static REAL ts[STEPS];

int main(void)
{
    FN(_controller_t) c;
    REAL s[NS], out[NU], xr[NX], ur[NU];
    double x[NX], u[NU];
    const double h = 1.0 / RATE;
    const double dt = h / SUBSTEPS;
    uint32_t start, total;
    uintptr_t sp;
    long k;
    int i, j, status = 0;

    start_counting();

    for (i = 0; i < NS; ++i) s[i] = (REAL)FN(_default_state)[i];
    for (i = 0; i < NX; ++i) x[i] = (double)FN(_default_state)[i];

    /* The stack: control calls, init and steps at a frozen state. */
    sp = stack_pointer();
    PAINT_BELOW(sp);
    status |= FN(_control)((REAL)0.5, s, NULL, REFS_HALF out);
    for (i = 0; i < NX; ++i) xr[i] = (REAL)x[i];
    status |= FN(_controller_init)(&c, (REAL)0.0, xr, NULL, NULL REFS_INIT);
    for (k = 0; k < 10; ++k) status |= FN(_controller_step)(&c, (REAL)(k * h), xr, REFS_STEP(k) ur);
    put_record("stack", used_below(sp), 0ul, 0);
    if (status != 0) {
        semihost_write0("fail\n");
        return 1;
    }

    start = now();
    for (k = 0; k < CALLS; ++k) status |= FN(_control)((REAL)0.5, s, NULL, REFS_HALF out);
    put_record("control", (unsigned long)CALLS, elapsed(start, now()), 1);

    /* A closed loop, untimed, recording what each step is given; then the same steps
     * again from init, timed together (one interval: the tick's 40 instructions of
     * resolution spread over every step). */
    for (i = 0; i < NX; ++i) xr[i] = (REAL)x[i];
    status |= FN(_controller_init)(&c, (REAL)0.0, xr, NULL, NULL REFS_INIT);
    for (k = 0; k < STEPS; ++k) {
        const double t = (double)k * h;
        ts[k] = (REAL)t;
        for (i = 0; i < NX; ++i) xs[k][i] = (REAL)x[i];
        status |= FN(_controller_step)(&c, ts[k], xs[k], REFS_STEP(k) ur);
        for (i = 0; i < NU; ++i) u[i] = (double)ur[i];
        for (j = 0; j < SUBSTEPS; ++j) status |= rk4(t + j * dt, dt, x, u);
    }
    status |= FN(_controller_init)(&c, (REAL)0.0, xs[0], NULL, NULL REFS_INIT);
    start = now();
    for (k = 0; k < STEPS; ++k) status |= FN(_controller_step)(&c, ts[k], xs[k], REFS_STEP(k) ur);
    total = elapsed(start, now());
    put_record("step", (unsigned long)STEPS, total, 1);
    if (status != 0) {
        semihost_write0("fail\n");
        return 1;
    }
    semihost_write0("end\n");
    return 0;
}
