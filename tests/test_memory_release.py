"""`tnn_dsl.core.memory.release_free_memory` and `large_blocks_mapped`: arrays of a few MB freed with smaller live
objects between them stay on glibc's heap (resident) until the first is called, and go back to the operating system
when it is, or at once when they were mapped on their own (the second). Run in fresh processes (the allocator's state
is per process). And `freeze_live_objects` (the collector's permanent generation), in this one."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from tnn_dsl.core.memory import _glibc

CHILD = r"""
import json, sys
import numpy as np
from tnn_dsl.core.memory import large_blocks_mapped, release_free_memory

def rss_mb():
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024

block = large_blocks_mapped() if sys.argv[1] == "mapped" else None
mapped = block.__enter__() if block is not None else False
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
if block is not None:  # left: blocks below 32 MiB come from the heap again and stay there when freed
    block.__exit__(None, None, None)
    again = [np.ones(8 * 2**20 // 8) for _ in range(5)]
    small = np.ones(2000)
    del again
    after_exit = rss_mb() - after
else:
    after_exit = 0.0
print(json.dumps({"applied": applied, "mapped": mapped, "grew": peak - before, "kept": after - before,
                  "kept_after_exit": after_exit}))
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


@pytest.mark.skipif(_glibc() is None, reason="glibc's mallopt only")
def test_large_blocks_mapped_go_back_when_freed_without_a_trim():
    mapped, off = _child("mapped"), _child("off")
    assert mapped["mapped"] and not mapped["applied"] and not off["mapped"]
    assert mapped["grew"] > 150
    assert mapped["kept"] < 40, mapped  # each 8 MB block was a mapping of its own, unmapped by `del`
    assert off["kept"] > 150, off
    assert mapped["kept_after_exit"] > 30, mapped  # glibc's behaviour after the block: heap blocks kept


def test_frozen_objects_leave_later_garbage_to_the_collector():
    """``freeze_live_objects``: what lives now goes to the permanent generation (walked by no later collection);
    a reference cycle made afterwards is still collected, and its finaliser runs."""
    import gc
    import weakref

    from tnn_dsl.core.memory import freeze_live_objects

    class Node:
        pass

    kept = Node()
    try:
        freeze_live_objects()
        assert gc.get_freeze_count() > 1000
        assert not any(o is kept for o in gc.get_objects())  # frozen: out of the generations the collector walks
        a, b = Node(), Node()
        a.other, b.other = b, a
        gone = weakref.ref(a)
        del a, b
        gc.collect()
        assert gone() is None
    finally:
        gc.unfreeze()
