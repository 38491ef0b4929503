/*
 * Start-up of the bare-metal images (Cortex-M4F on mps2-an386, Cortex-M7 on mps2-an500):
 * the vector table, the reset handler and a fault handler that reports and stops.
 *
 * The reset handler enables the FPU before anything else runs: the hard-float ABI
 * passes reals in FPU registers, and the first floating-point instruction with the
 * coprocessor off would fault. Then it copies .data from flash, zeroes .bss and calls
 * main; main's return value ends the QEMU process through semihosting.
 */
#include <stdint.h>

#include "semihost.h"

extern uint32_t _sidata, _sdata, _edata, _sbss, _ebss, _estack;
extern int main(void);

void Reset_Handler(void);
void Fault_Handler(void);

/* CPACR: full access to coprocessors 10 and 11, the FPU (ARMv7-M ARM, B3.2.20). */
#define CPACR (*(volatile uint32_t *)0xE000ED88u)

void Reset_Handler(void)
{
    uint32_t *src = &_sidata;
    uint32_t *dst;

    CPACR |= (0xFu << 20);
    __asm__ volatile("dsb\n\tisb" ::: "memory");
    for (dst = &_sdata; dst < &_edata;) {
        *dst++ = *src++;
    }
    for (dst = &_sbss; dst < &_ebss;) {
        *dst++ = 0u;
    }
    semihost_exit(main());
}

/* A fault (a bad address, an undefined instruction) ends the run with a message, where
 * the core would otherwise spin in the handler until the test's timeout. */
void Fault_Handler(void)
{
    semihost_write0("FAULT\n");
    semihost_exit(3);
}

/* The vector table: the initial stack pointer, then the handlers (exceptions 1-15). */
__attribute__((section(".isr_vector"), used)) static void (*const vectors[16])(void) = {
    (void (*)(void))(&_estack),
    Reset_Handler,
    Fault_Handler, /* NMI */
    Fault_Handler, /* HardFault */
    Fault_Handler, /* MemManage */
    Fault_Handler, /* BusFault */
    Fault_Handler, /* UsageFault */
    0, 0, 0, 0,
    Fault_Handler, /* SVCall */
    Fault_Handler, /* DebugMonitor */
    0,
    Fault_Handler, /* PendSV */
    Fault_Handler, /* SysTick */
};
