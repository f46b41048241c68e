"""`tnn_dsl.core.memory.release_free_memory`: arrays of a few MB freed with smaller live objects between them stay
on glibc's heap (resident) until it is called, and go back to the operating system when it is. Run in fresh
processes (the allocator's state is per process)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from tnn_dsl.core.memory import _glibc

CHILD = r"""
import json, sys
import numpy as np
from tnn_dsl.core.memory import release_free_memory

def rss_mb():
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024

big = np.ones(20 * 2**20 // 8)  # 20 MB, mapped on its own; freeing it raises glibc's mmap threshold to 20 MB,
# so the 8 MB arrays below come from the heap
del big
before = rss_mb()
held, kept = [], []
for _ in range(25):  # 25 x 8 MB = 200 MB, each followed by a small array that stays (as results do)
    held.append(np.ones(8 * 2**20 // 8))
    kept.append(np.ones(2000))
peak = rss_mb()
del held
applied = release_free_memory() if sys.argv[1] == "on" else False
after = rss_mb()
print(json.dumps({"applied": applied, "grew": peak - before, "kept": after - before}))
"""


def _child(mode: str) -> dict:
    out = subprocess.run([sys.executable, "-c", CHILD, mode], capture_output=True, text=True, timeout=120,
                         env={"PATH": "/usr/bin:/bin"}, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.skipif(_glibc() is None, reason="glibc's mallopt only")
def test_freed_arrays_go_back_to_the_system_only_with_the_setting():
    on, off = _child("on"), _child("off")
    assert on["applied"] and not off["applied"]
    assert on["grew"] > 150 and off["grew"] > 150
    assert on["kept"] < 40, on  # returned
    assert off["kept"] > 150, off  # glibc's default keeps them: the test can tell

