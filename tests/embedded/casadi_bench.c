/*
 * CasADi's generated C of the same law (benchmarks/bench_c.py's casadi_law), counted as
 * bench.c counts ours: instructions per call under `-icount shift=0`, and its stack.
 *
 * Built with -DSTATE='{...}' -DPARAMS='{...}' (the example's default closed-loop state
 * and parameters, as double literals), -DCALLS=<n>, and casadi_real as CasADi's code
 * generator was told (double, or float). With -DREFS='{...}' (a spec with references
 * measured at run time) the law takes the references' jets as its fourth argument.
 */
#include "casadi_law.h"
#include "counting.h"

static const double state[] = STATE;
static const double parameters[] = PARAMS;
#define NS (sizeof state / sizeof state[0])
#define NP (sizeof parameters / sizeof parameters[0])
#ifdef REFS
static const double jets[] = REFS;
#define NJ (sizeof jets / sizeof jets[0])
#endif

static casadi_real w[8192];
static casadi_int iw[256];
static const casadi_real *arg[64];
static casadi_real *res[64];

int main(void)
{
    casadi_real t = (casadi_real)0.5;
    casadi_real s[NS], p[NP], out[64];
#ifdef REFS
    casadi_real r[NJ];
#endif
    casadi_int n_arg, n_res, n_iw, n_w;
    uint32_t start;
    uintptr_t sp;
    long k;
    int status = 0;
    size_t i;

    start_counting();
    if (casadi_law_work(&n_arg, &n_res, &n_iw, &n_w) != 0 || n_w > 8192 || n_iw > 256
        || n_arg > 64 || n_res > 64) {
        semihost_write0("fail work\n");
        return 1;
    }
    for (i = 0; i < NS; ++i) s[i] = (casadi_real)state[i];
    for (i = 0; i < NP; ++i) p[i] = (casadi_real)parameters[i];
    arg[0] = &t;
    arg[1] = s;
    arg[2] = p;
#ifdef REFS
    for (i = 0; i < NJ; ++i) r[i] = (casadi_real)jets[i];
    arg[3] = r;
#endif
    res[0] = out;

    sp = stack_pointer();
    PAINT_BELOW(sp);
    status |= casadi_law(arg, res, iw, w, 0);
    put_record("stack", used_below(sp), 0ul, 0);

    start = now();
    for (k = 0; k < CALLS; ++k) status |= casadi_law(arg, res, iw, w, 0);
    put_record("control", (unsigned long)CALLS, elapsed(start, now()), 1);
    if (status != 0) {
        semihost_write0("fail\n");
        return 1;
    }
    semihost_write0("end\n");
    return 0;
}
