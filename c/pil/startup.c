/* Reset and start of the PIL image (c/pil): the smallest startup a Cortex-M needs. The vector
 * table holds the initial stack pointer and the reset handler; every other exception stops the
 * run (an exception here is a bug: nothing enables interrupts). The reset handler turns the FPU
 * on, copies .data from flash to RAM, clears .bss and calls main; main's return value leaves
 * QEMU as its exit code (semihosting). Symbols from pil.ld. */
#include <stdint.h>

#include "semihost.h"

extern uint32_t __data_load, __data_start, __data_end, __bss_start, __bss_end, __stack_top;
extern int main(void);

void reset_handler(void);
static void fault_handler(void);

/* the vector table: SP, then reset, NMI, HardFault, MemManage, BusFault, UsageFault */
__attribute__((section(".vectors"), used)) static const uintptr_t vectors[7] = {
    (uintptr_t)&__stack_top, (uintptr_t)reset_handler, (uintptr_t)fault_handler,
    (uintptr_t)fault_handler, (uintptr_t)fault_handler, (uintptr_t)fault_handler,
    (uintptr_t)fault_handler,
};

#define CPACR (*(volatile uint32_t *)0xE000ED88u)

void reset_handler(void)
{
    uint32_t *src = &__data_load, *dst;
    CPACR |= 0xFu << 20;                  /* CP10 and CP11 (the FPU): full access */
    __asm volatile("dsb\n\tisb" ::: "memory");
    for (dst = &__data_start; dst < &__data_end;) *dst++ = *src++;
    for (dst = &__bss_start; dst < &__bss_end;) *dst++ = 0;
    sh_exit(main());
}

static void fault_handler(void)
{
    sh_exit(3);
}
