/*
 * Counting instructions and stack on the bare-metal boards, for bench.c and
 * casadi_bench.c (the text of bench.c says how the count works).
 */
#ifndef COUNTING_H
#define COUNTING_H

#include <stdint.h>
#include <string.h>

#include "semihost.h"

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

extern uint32_t _ebss;
#define PAINT 0xA5A5A5A5u

static uintptr_t stack_pointer(void)
{
    uintptr_t sp;
    __asm__ volatile("mov %0, sp" : "=r"(sp));
    return sp;
}

/* Fill the free stack with PAINT, from the end of .bss to 8 bytes below `sp` (the
 * caller's stack pointer, from stack_pointer()). A macro, not a function: a function's
 * own frame would sit in the region it paints. Nothing below the stack pointer is live
 * (the ARM ABIs have no red zone). */
#define PAINT_BELOW(sp)                                                          \
    do {                                                                         \
        uint32_t *word_;                                                         \
        for (word_ = &_ebss; (uintptr_t)(word_ + 2) < (sp); ++word_) *word_ = PAINT; \
    } while (0)

/* The bytes of stack used below `sp` since paint: down to the lowest word not PAINT. */
static unsigned long used_below(uintptr_t sp)
{
    const uint32_t *word = &_ebss;
    while ((uintptr_t)word < sp && *word == PAINT) ++word;
    return (unsigned long)(sp - (uintptr_t)word);
}

/* Start SysTick from the core clock and print the calibration record: the ticks of
 * 1,000,000 iterations of the 2-instruction loop. */
static void start_counting(void)
{
    uint32_t start;
    SYST_RVR = TICK_MASK;
    SYST_CVR = 0u;
    SYST_CSR = 5u; /* enabled, core clock, no interrupt */
    start = now();
    spin(1000000u);
    put_record("calibrate", 1000000ul, elapsed(start, now()), 1);
}

#endif
