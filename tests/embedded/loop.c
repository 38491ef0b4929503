/*
 * The closed loop every target runs: the generated controller stepped at a fixed rate,
 * the plant integrated in double between steps under a zero-order hold.
 *
 * The plant is the generated `<name>_plant` (the spec's model) compiled in double and
 * renamed `harness_plant` (harness.py), so that a single-precision controller runs against
 * the same double plant as a double one. Between two controller steps, SUBSTEPS steps of
 * the classical fourth-order Runge-Kutta method advance it.
 *
 * Built with -DNAME=<name> -DUNAME=<NAME> -DREAL=<double|float> -DSTEPS=<n> -DRATE=<Hz>
 * -DSUBSTEPS=<n> -DEVERY=<n>. An example with references measured at run time
 * ([references]) is built with -DREFS and the include path of a "loop_refs.h" that
 * defines refs_at[STEPS + 1][<NAME>_N_REFERENCE_JET], the references' jets at each
 * step's time k / RATE (init takes row 0). The output is text, one record a line, every number the 16
 * hexadecimal digits of a double's bits (exact, and no printf needed on bare metal):
 *   s <k> <t> <x_0> ... <x_{n-1}> <u_0> ... <u_{m-1}>   every EVERY steps and the last
 *   fail <k> <status>                                   a step that failed
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

/* The references' jets, one more argument of controller_init and controller_step
 * (docs/references.md); nothing at all without references. */
#ifdef REFS
#include "loop_refs.h"
#define REFS_STEP(k) refs_at[k],
#define REFS_INIT , refs_at[0]
#else
#define REFS_STEP(k)
#define REFS_INIT
#endif

int harness_plant(double t, const double *x, const double *u, const double *params, double *out);

static char line[64 + 17 * (2 + NX + NU)];
static size_t used;

static void put_text(const char *text)
{
    size_t n = strlen(text);
    memcpy(line + used, text, n);
    used += n;
}

static void put_hex(double value)
{
    static const char digits[] = "0123456789abcdef";
    uint64_t bits;
    int shift;
    memcpy(&bits, &value, sizeof bits);
    line[used++] = ' ';
    for (shift = 60; shift >= 0; shift -= 4) {
        line[used++] = digits[(bits >> shift) & 0xFu];
    }
}

static void put_int(long value)
{
    char text[24];
    int n = 0;
    unsigned long magnitude = value < 0 ? (unsigned long)-value : (unsigned long)value;
    do {
        text[n++] = (char)('0' + magnitude % 10u);
        magnitude /= 10u;
    } while (magnitude != 0u);
    if (value < 0) {
        text[n++] = '-';
    }
    line[used++] = ' ';
    while (n > 0) {
        line[used++] = text[--n];
    }
}

static void flush(void)
{
    line[used++] = '\n';
    line[used] = '\0';
    semihost_write0(line);
    used = 0;
}

/* One classical Runge-Kutta step of the plant from (t, x) over h, u held. */
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

static void record(long k, double t, const double *x, const double *u)
{
    int i;
    put_text("s");
    put_int(k);
    put_hex(t);
    for (i = 0; i < NX; ++i) put_hex(x[i]);
    for (i = 0; i < NU; ++i) put_hex(u[i]);
    flush();
}

static int fail(long k, int status)
{
    put_text("fail");
    put_int(k);
    put_int(status);
    flush();
    return 1;
}

int main(void)
{
    FN(_controller_t) c;
    double x[NX], u[NU];
    REAL xr[NX], ur[NU];
    const double h = 1.0 / RATE;
    const double dt = h / SUBSTEPS;
    long k;
    int i, j, status;

    for (i = 0; i < NX; ++i) {
        x[i] = (double)FN(_default_state)[i];
        xr[i] = (REAL)x[i];
    }
    status = FN(_controller_init)(&c, (REAL)0.0, xr, NULL, NULL REFS_INIT);
    if (status != 0) return fail(-1, status);
    for (k = 0; k <= STEPS; ++k) {
        const double t = (double)k * h;
        for (i = 0; i < NX; ++i) xr[i] = (REAL)x[i];
        status = FN(_controller_step)(&c, (REAL)t, xr, REFS_STEP(k) ur);
        if (status != 0) return fail(k, status);
        for (i = 0; i < NU; ++i) u[i] = (double)ur[i];
        if (k % EVERY == 0 || k == STEPS) record(k, t, x, u);
        if (k == STEPS) break;
        for (j = 0; j < SUBSTEPS; ++j) {
            status = rk4(t + j * dt, dt, x, u);
            if (status != 0) return fail(k, 100 + status);
        }
    }
    put_text("end");
    flush();
    return 0;
}
