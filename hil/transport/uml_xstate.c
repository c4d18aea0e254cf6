/* LD_PRELOAD shim for User-mode Linux on hosts whose XSAVE area is larger than UML's.
 *
 * UML saves and restores the FPU state of its guest processes with
 * ptrace(PTRACE_GETREGSET/PTRACE_SETREGSET, NT_X86_XSTATE) through a buffer of its own size
 * (2696 bytes in Debian's 6.1 build: x87/SSE, AVX, AVX-512 and PKRU). The host kernel accepts a
 * short GETREGSET but refuses a SETREGSET that is not exactly its full XSAVE size with EFAULT
 * (arch/x86/kernel/fpu/regset.c), and a host with AMX (8 KiB of tile data) has a larger one, so
 * UML panics at the first context switch: "userspace - ptrace set fp regs failed, errno = 14".
 *
 * This wrapper retries such a refused SETREGSET with a buffer of the host's size: UML's bytes
 * first, zeros after, and every state component that does not lie wholly inside UML's bytes
 * marked as in its initial state (its XSTATE_BV bit cleared), which is what it is in a guest:
 * UML's guests never enable AMX (it needs a permission request that UML does not pass on).
 * Every other call, and every call that succeeds, goes to libc unchanged, so on hosts where
 * UML works the shim does nothing.
 *
 * Built by hil/transport/vcan.py with the host's gcc, cached, and preloaded into linux.uml only. */
#define _GNU_SOURCE
#include <cpuid.h>
#include <dlfcn.h>
#include <errno.h>
#include <stdarg.h>
#include <stdint.h>
#include <string.h>
#include <sys/types.h>
#include <sys/uio.h>

#define REQ_GETREGSET 0x4204
#define REQ_SETREGSET 0x4205
#define NT_X86_XSTATE_NOTE 0x202
#define XSAVE_HEADER 512            /* XSTATE_BV: the first 8 bytes of the XSAVE header */
#define XSAVE_MIN (XSAVE_HEADER + 64)
#define BUF_MAX 65536

typedef long (*ptrace_fn)(int, pid_t, void *, void *);

static unsigned char full[BUF_MAX] __attribute__((aligned(64)));
static size_t host_size;

long ptrace(int request, ...)
{
    static ptrace_fn real;
    va_list ap;
    va_start(ap, request);
    pid_t pid = va_arg(ap, pid_t);
    void *addr = va_arg(ap, void *);
    void *data = va_arg(ap, void *);
    va_end(ap);
    if (!real)
        real = (ptrace_fn)dlsym(RTLD_NEXT, "ptrace");

    long rc = real(request, pid, addr, data);
    if (rc == 0 || errno != EFAULT || request != REQ_SETREGSET
        || (uintptr_t)addr != NT_X86_XSTATE_NOTE || data == NULL)
        return rc;
    const struct iovec *iov = data;
    if (!host_size) {               /* the kernel says its size: a GETREGSET's iov_len */
        struct iovec probe = { full, BUF_MAX };
        if (real(REQ_GETREGSET, pid, addr, &probe) != 0)
            goto refused;
        host_size = probe.iov_len;
    }
    if (iov->iov_len < XSAVE_MIN || iov->iov_len >= host_size)
        goto refused;
    memset(full, 0, host_size);
    memcpy(full, iov->iov_base, iov->iov_len);
    uint64_t bv;
    memcpy(&bv, full + XSAVE_HEADER, sizeof bv);
    for (unsigned i = 2; i < 63; i++) {     /* components 0, 1 (x87, SSE) are in the legacy area */
        unsigned size, offset, ecx, edx;
        if (!(bv >> i & 1))
            continue;
        __cpuid_count(0xd, i, size, offset, ecx, edx);
        if ((size_t)offset + size > iov->iov_len)
            bv &= ~(1ULL << i);
    }
    memcpy(full + XSAVE_HEADER, &bv, sizeof bv);
    struct iovec padded = { full, host_size };
    return real(REQ_SETREGSET, pid, addr, &padded);

refused:
    errno = EFAULT;
    return -1;
}
