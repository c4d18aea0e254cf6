"""The compiled AES-CMAC (hil/kernels/cmac.py, libcrypto by symbol) against the cryptography
package's, and cached like every kernel."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from cryptography.hazmat.primitives.ciphers import algorithms
from cryptography.hazmat.primitives.cmac import CMAC

from hil.kernels.cmac import Cmac, cmac

ROOT = Path(__file__).resolve().parents[1]


def test_compiled_cmac_is_the_cryptography_packages():
    rng = np.random.default_rng(7)
    for _ in range(300):
        key = rng.bytes(16)
        c = Cmac(key)
        for n in (0, 1, 15, 16, 17, 22, 64):
            msg = np.frombuffer(rng.bytes(n), np.uint8).copy() if n else np.zeros(1, np.uint8)
            assert cmac(c.ctx, msg, n, c.tag16, c.length)
            ref = CMAC(algorithms.AES(key))
            ref.update(bytes(msg[:n]))
            assert int(c.length[0]) == 16
            assert c.tag16.tobytes() == ref.finalize(), (key.hex(), n)


def test_a_key_of_another_length_is_refused():
    with pytest.raises(ValueError):
        Cmac(bytes(15))


def test_the_kernel_loads_from_the_cache_in_a_new_process():
    code = ("import hil, json, numpy as np; from hil.kernels.cmac import Cmac, cmac; "
            "c = Cmac(bytes(range(16))); m = np.arange(20, dtype=np.uint8); "
            "ok = cmac(c.ctx, m, 20, c.tag16, c.length); "
            "print(json.dumps([bool(ok), c.tag16.tobytes().hex(), "
            "sum(cmac.stats.cache_hits.values()), sum(cmac.stats.cache_misses.values())]))")
    runs = [json.loads(subprocess.run([sys.executable, "-c", code], cwd=ROOT, check=True,
                                      capture_output=True, text=True, env=dict(os.environ)
                                      ).stdout) for _ in range(2)]
    ref = CMAC(algorithms.AES(bytes(range(16))))
    ref.update(bytes(range(20)))
    want = ref.finalize().hex()
    for ok, tag, _, _ in runs:
        assert ok and tag == want
    assert runs[1][2] == 1 and runs[1][3] == 0        # the second process: from the cache
