"""glibc's heap kept for the next step (cnnps.train.allocator), by glibc's own accounting."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

_HEAP = """
import ctypes, ctypes.util, json, sys
from cnnps.train.allocator import keep_freed_memory
took = keep_freed_memory() if sys.argv[1] == "keep" else False
libc = ctypes.CDLL(ctypes.util.find_library("c"))
names = ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks", "fordblks", "keepcost")
class Info(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in names]
libc.mallinfo2.restype = Info
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
block = libc.malloc(16 << 20)  # 16 MB, the size of a training activation
held = libc.mallinfo2().hblkhd
libc.free(block)
print(json.dumps({"took": took, "mmapped_while_held": held, "kept_after_free": libc.mallinfo2().fordblks}))
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt")
def test_keep_freed_memory_keeps_large_blocks_in_the_heap():
    """glibc as it comes maps a 16 MB block on its own and unmaps it on free (the next step
    faults it in again); once kept, the block comes from the heap and stays there, free,
    for the next step (glibc's own accounting, mallinfo2). The user's MALLOC_ settings win."""
    def run(mode, **env):
        e = {k: v for k, v in os.environ.items() if not k.startswith("MALLOC_")}
        e.update(env)
        out = subprocess.run([sys.executable, "-c", _HEAP, mode], capture_output=True, text=True, env=e)
        if out.returncode:
            pytest.skip(f"no glibc mallinfo2 here: {out.stderr.strip().splitlines()[-1:]}")
        return json.loads(out.stdout.strip().splitlines()[-1])

    kept, plain = run("keep"), run("plain")
    if not kept["took"]:
        pytest.skip("not glibc: mallopt unavailable")
    block = 16 << 20
    assert plain["mmapped_while_held"] >= block and plain["kept_after_free"] < block, plain
    assert kept["mmapped_while_held"] < block <= kept["kept_after_free"], kept
    assert run("keep", MALLOC_TRIM_THRESHOLD_="131072")["took"] is False
