/* ARM semihosting (the "Semihosting for AArch32 and AArch64" specification), the few calls the
 * PIL harness needs: a call is `bkpt 0xab` with the operation in r0 and its argument (a pointer
 * to a parameter block) in r1; QEMU (-semihosting) serves it on the host, files relative to
 * QEMU's working directory. */
#ifndef PIL_SEMIHOST_H
#define PIL_SEMIHOST_H

#include <stdint.h>

#define SH_OPEN 0x01
#define SH_CLOSE 0x02
#define SH_WRITE 0x05
#define SH_READ 0x06
#define SH_EXIT_EXTENDED 0x20

static inline int32_t sh_call(int32_t op, const void *arg)
{
    register int32_t r0 __asm__("r0") = op;
    register const void *r1 __asm__("r1") = arg;
    __asm volatile("bkpt 0xab" : "+r"(r0) : "r"(r1) : "memory");
    return r0;
}

/* open a host file: mode 0 "r", 1 "rb", 4 "w", 5 "wb"; a handle, or -1 */
static inline int32_t sh_open(const char *name, uint32_t len, uint32_t mode)
{
    uint32_t block[3];
    block[0] = (uint32_t)name;
    block[1] = mode;
    block[2] = len;
    return sh_call(SH_OPEN, block);
}

/* read n bytes: returns how many were NOT read (0: all) */
static inline int32_t sh_read(int32_t fd, void *buf, uint32_t n)
{
    uint32_t block[3];
    block[0] = (uint32_t)fd;
    block[1] = (uint32_t)buf;
    block[2] = n;
    return sh_call(SH_READ, block);
}

/* write n bytes: returns how many were NOT written (0: all) */
static inline int32_t sh_write(int32_t fd, const void *buf, uint32_t n)
{
    uint32_t block[3];
    block[0] = (uint32_t)fd;
    block[1] = (uint32_t)buf;
    block[2] = n;
    return sh_call(SH_WRITE, block);
}

static inline void sh_close(int32_t fd)
{
    uint32_t block[1];
    block[0] = (uint32_t)fd;
    sh_call(SH_CLOSE, block);
}

/* leave QEMU with exit code `code` (ADS_Stopped_ApplicationExit) */
__attribute__((noreturn)) static inline void sh_exit(int code)
{
    uint32_t block[2];
    block[0] = 0x20026u;
    block[1] = (uint32_t)code;
    sh_call(SH_EXIT_EXTENDED, block);
    for (;;) {
    }
}

#endif /* PIL_SEMIHOST_H */
