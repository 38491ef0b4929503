/*
 * Semihosting (ARM's "Semihosting for AArch32 and AArch64"): on M-profile, `bkpt 0xAB`
 * with the operation in r0 and its argument in r1; QEMU serves it when started with
 * `-semihosting-config enable=on,target=native`. On a hosted system (the Linux
 * binaries and the x86-64 reference) the same two calls are stdio's.
 */
#include "semihost.h"

#if defined(__ARM_ARCH_7EM__) && !defined(__linux__)

#define SYS_WRITE0 0x04
#define SYS_EXIT 0x18
#define ADP_STOPPED_APPLICATION_EXIT 0x20026
#define ADP_STOPPED_RUN_TIME_ERROR 0x20023

static int semihost_call(int op, const void *arg)
{
    register int r0 __asm__("r0") = op;
    register const void *r1 __asm__("r1") = arg;
    __asm__ volatile("bkpt 0xAB" : "+r"(r0) : "r"(r1) : "memory");
    return r0;
}

void semihost_write0(const char *text)
{
    (void)semihost_call(SYS_WRITE0, text);
}

void semihost_exit(int status)
{
    /* AArch32's SYS_EXIT carries no exit code: QEMU exits 0 for ApplicationExit and 1
     * for any other reason. */
    (void)semihost_call(SYS_EXIT, (const void *)(status == 0 ? ADP_STOPPED_APPLICATION_EXIT
                                                             : ADP_STOPPED_RUN_TIME_ERROR));
    for (;;) {
    }
}

#else

#include <stdio.h>
#include <stdlib.h>

void semihost_write0(const char *text)
{
    fputs(text, stdout);
}

void semihost_exit(int status)
{
    fflush(stdout);
    exit(status);
}

#endif
