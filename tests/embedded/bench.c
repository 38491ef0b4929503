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
 * -DCALLS=<n>. Prints, one record a line (decimal integers):
 *   calibrate <iterations of a 2-instruction loop> <ticks>
 *   control <calls> <ticks>
 *   step <steps> <ticks>          the controller steps of a closed loop, each timed alone
 *   stack <bytes>                 the deepest stack of init, steps and control calls
 *   end
 */
#include <stdint.h>
#include <string.h>

#include "semihost.h"

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

int harness_plant(double t, const double *x, const double *u, const double *params, double *out);

/* SysTick (ARMv7-M ARM, B3.3): a 24-bit down-counter. */
#define SYST_CSR (*(volatile uint32_t *)0xE000E010u)
#define SYST_RVR (*(volatile uint32_t *)0xE000E014u)
#define SYST_CVR (*(volatile uint32_t *)0xE000E018u)
#define TICK_MASK 0x00FFFFFFu

static uint32_t now(void)
{
    return SYST_CVR;
}

/* Ticks from `start` to `end` of the down-counter (one wrap at most). */
static uint32_t elapsed(uint32_t start, uint32_t end)
{
    return (start - end) & TICK_MASK;
}

static void put_record(const char *key, unsigned long a, unsigned long b, int two)
{
    char line[80];
    char digits[24];
    size_t used = strlen(key);
    unsigned long values[2];
    int v;
    memcpy(line, key, used);
    values[0] = a;
    values[1] = b;
    for (v = 0; v < (two ? 2 : 1); ++v) {
        int n = 0;
        unsigned long m = values[v];
        do {
            digits[n++] = (char)('0' + m % 10u);
            m /= 10u;
        } while (m != 0u);
        line[used++] = ' ';
        while (n > 0) line[used++] = digits[--n];
    }
    line[used++] = '\n';
    line[used] = '\0';
    semihost_write0(line);
}

/* n iterations of exactly two instructions (subs, bne). */
static void spin(uint32_t n)
{
    __asm__ volatile("1: subs %0, %0, #1\n\tbne 1b" : "+r"(n)::"cc");
}

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

extern uint32_t _ebss;
#define PAINT 0xA5A5A5A5u

static uintptr_t stack_pointer(void)
{
    uintptr_t sp;
    __asm__ volatile("mov %0, sp" : "=r"(sp));
    return sp;
}

/* Fill the free stack with PAINT, from the end of .bss to 64 words below this frame. */
static __attribute__((noinline)) void paint(void)
{
    uint32_t here;
    uint32_t *word;
    for (word = &_ebss; word < &here - 64; ++word) *word = PAINT;
}

/* The bytes of stack used below `sp` since paint: down to the lowest word not PAINT. */
static unsigned long used_below(uintptr_t sp)
{
    const uint32_t *word = &_ebss;
    while ((uintptr_t)word < sp && *word == PAINT) ++word;
    return (unsigned long)(sp - (uintptr_t)word);
}

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

    SYST_RVR = TICK_MASK;
    SYST_CVR = 0u;
    SYST_CSR = 5u; /* enabled, core clock, no interrupt */

    start = now();
    spin(1000000u);
    put_record("calibrate", 1000000ul, elapsed(start, now()), 1);

    for (i = 0; i < NS; ++i) s[i] = (REAL)FN(_default_state)[i];
    for (i = 0; i < NX; ++i) x[i] = (double)FN(_default_state)[i];

    /* The stack: control calls, init and steps at a frozen state. */
    sp = stack_pointer();
    paint();
    status |= FN(_control)((REAL)0.5, s, NULL, out);
    for (i = 0; i < NX; ++i) xr[i] = (REAL)x[i];
    status |= FN(_controller_init)(&c, (REAL)0.0, xr, NULL, NULL);
    for (k = 0; k < 10; ++k) status |= FN(_controller_step)(&c, (REAL)(k * h), xr, ur);
    put_record("stack", used_below(sp), 0ul, 0);
    if (status != 0) {
        semihost_write0("fail\n");
        return 1;
    }

    start = now();
    for (k = 0; k < CALLS; ++k) status |= FN(_control)((REAL)0.5, s, NULL, out);
    put_record("control", (unsigned long)CALLS, elapsed(start, now()), 1);

    /* A closed loop, only its controller steps timed. */
    total = 0u;
    for (i = 0; i < NX; ++i) xr[i] = (REAL)x[i];
    status |= FN(_controller_init)(&c, (REAL)0.0, xr, NULL, NULL);
    for (k = 0; k < STEPS; ++k) {
        const double t = (double)k * h;
        for (i = 0; i < NX; ++i) xr[i] = (REAL)x[i];
        start = now();
        status |= FN(_controller_step)(&c, (REAL)t, xr, ur);
        total += elapsed(start, now());
        for (i = 0; i < NU; ++i) u[i] = (double)ur[i];
        for (j = 0; j < SUBSTEPS; ++j) status |= rk4(t + j * dt, dt, x, u);
    }
    put_record("step", (unsigned long)STEPS, total, 1);
    if (status != 0) {
        semihost_write0("fail\n");
        return 1;
    }
    semihost_write0("end\n");
    return 0;
}
