/*
 * The smallest program that runs the controller: init, then a step, as firmware would
 * (no plant, no output). Its image's size is what the controller costs in flash and RAM
 * with the library routines it pulls in (libm, and on the M4F libgcc's software double).
 * Built with -DNAME, -DUNAME and -DREAL like loop.c, and with -DREFS='{...}' (one jet of
 * <NAME>_N_REFERENCE_JET values) for an example with references measured at run time.
 */
#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)
#define STR_(a) #a
#define STR(a) STR_(a)
#include STR(NAME.h)

#include "semihost.h"

#define FN(suffix) CAT(NAME, suffix)
#define CONST(suffix) CAT(UNAME, suffix)

#ifdef REFS
static const REAL refs[CONST(_N_REFERENCE_JET)] = REFS;
#define REFS_ARG refs,
#define REFS_LAST , refs
#else
#define REFS_ARG
#define REFS_LAST
#endif

int main(void)
{
    static FN(_controller_t) c;
    REAL u[CONST(_N_INPUTS)];
    int status = FN(_controller_init)(&c, (REAL)0.0, FN(_default_state), NULL, NULL REFS_LAST);
    status |= FN(_controller_step)(&c, (REAL)0.01, FN(_default_state), REFS_ARG u);
    return status;
}
