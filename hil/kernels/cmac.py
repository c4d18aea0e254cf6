"""AES-128 CMAC (NIST SP 800-38B) from OpenSSL's libcrypto, for compiled code: the SecOC
authenticator of a frame without leaving the compiled tick (``hil.transport.secoc`` computes the same
with the ``cryptography`` package, which binds the same library).

libcrypto's ``CMAC_*`` functions are bound by symbol (``firmware.kernels.external``), so the
kernels that call them stay in numba's cache: the symbols are resolved when the cached code
loads, from the library loaded here. A ``Cmac`` owns one keyed context (``CMAC_CTX``); a
compiled caller gets its address (``ctx``) and scratch (``tag16``, ``length``).
"""

from __future__ import annotations

import ctypes
import ctypes.util

import numpy as np

from firmware.kernels import INTERPRETED, external, load_library, njit

KEY_BYTES = 16


def _library() -> str:
    name = ctypes.util.find_library("crypto")
    if not name:
        raise OSError("OpenSSL's libcrypto is not installed (Debian: libssl3)")
    return name


_NAME = _library()
load_library(_NAME)
_lib = ctypes.CDLL(_NAME)
_lib.CMAC_CTX_new.restype = ctypes.c_void_p
_lib.CMAC_CTX_free.argtypes = (ctypes.c_void_p,)
_lib.EVP_aes_128_cbc.restype = ctypes.c_void_p
_lib.CMAC_Init.argtypes = (ctypes.c_void_p, ctypes.c_char_p, ctypes.c_size_t, ctypes.c_void_p,
                           ctypes.c_void_p)

CMAC_Init = external("CMAC_Init", "int32", "voidptr", "voidptr", "uint64", "voidptr",
                     "voidptr")
CMAC_Update = external("CMAC_Update", "int32", "voidptr", "voidptr", "uint64")
CMAC_Final = external("CMAC_Final", "int32", "voidptr", "voidptr", "voidptr")


class Cmac:
    """One AES-128 key's CMAC context, for compiled callers (``ctx``); freed with the
    object."""

    def __init__(self, key: bytes):
        if len(key) != KEY_BYTES:
            raise ValueError(f"an AES-128 key is {KEY_BYTES} bytes")
        self.tag16 = np.zeros(16, np.uint8)       # (the whole tag, then truncated)
        self.length = np.zeros(1, np.uint64)
        if INTERPRETED:                           # (the interpreter's cmac: the key's handle)
            self.ctx = len(_KEYS) + 1
            _KEYS[self.ctx] = bytes(key)
            return
        self.ctx = _lib.CMAC_CTX_new()
        if not self.ctx or _lib.CMAC_Init(self.ctx, bytes(key), KEY_BYTES,
                                          _lib.EVP_aes_128_cbc(), None) != 1:
            raise OSError("libcrypto: CMAC_Init failed")

    def __del__(self):
        if getattr(self, "ctx", None) and not INTERPRETED:
            _lib.CMAC_CTX_free(self.ctx)
            self.ctx = None

    def __deepcopy__(self, memo):                 # (a context does not copy)
        raise TypeError("a Cmac context is not copied; make another with the key")


@njit
def cmac(ctx, msg, n, tag16, length) -> bool:
    """The CMAC of ``msg[:n]`` into ``tag16`` (the context keeps its key: it starts again
    here); False where libcrypto fails."""
    if CMAC_Init(ctx, 0, 0, 0, 0) != 1:
        return False
    if CMAC_Update(ctx, msg.ctypes.data, n) != 1:
        return False
    return CMAC_Final(ctx, tag16.ctypes.data, length.ctypes.data) == 1


_KEYS: dict[int, bytes] = {}      # NUMBA_DISABLE_JIT=1: the keys by handle


if INTERPRETED:
    def cmac(ctx, msg, n, tag16, length) -> bool:     # noqa: F811 - the interpreter's
        """``cmac`` run by the interpreter (numba's external functions are not callable
        there): the ``cryptography`` package's CMAC, which binds the same libcrypto."""
        from cryptography.hazmat.primitives.ciphers import algorithms
        from cryptography.hazmat.primitives.cmac import CMAC

        c = CMAC(algorithms.AES(_KEYS[ctx]))
        c.update(bytes(msg[:n]))
        tag16[:] = np.frombuffer(c.finalize(), np.uint8)
        length[0] = 16
        return True
