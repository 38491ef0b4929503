/*
 * The smallest program that runs the controller: init, then a step, as firmware would
 * (no plant, no output). Its image's size is what the controller costs in flash and RAM
 * with the library routines it pulls in (libm, and on the M4F libgcc's software double).
 * Built with -DNAME, -DUNAME and -DREAL like loop.c.
 */
#define CAT_(a, b) a##b
#define CAT(a, b) CAT_(a, b)
#define STR_(a) #a
#define STR(a) STR_(a)
#include STR(NAME.h)

#include "semihost.h"

#define FN(suffix) CAT(NAME, suffix)
#define CONST(suffix) CAT(UNAME, suffix)

int main(void)
{
    static FN(_controller_t) c;
    REAL u[CONST(_N_INPUTS)];
    int status = FN(_controller_init)(&c, (REAL)0.0, FN(_default_state), NULL, NULL);
    status |= FN(_controller_step)(&c, (REAL)0.01, FN(_default_state), u);
    return status;
}
