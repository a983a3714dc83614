"""The C allocator keeps a long take's large arrays (mocapskel.solvers.allocator): on glibc a large array comes from
the heap, not a mapping of its own, and its memory stays in the heap for the next array when it is freed."""
import ctypes
import os
import subprocess
import sys

import pytest

_PROBE = r"""
import ctypes, sys
import numpy as np
if sys.argv[1] == "1":
    from mocapskel.solvers.allocator import keep_large_blocks
    keep_large_blocks()
class Info(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                 "fsmblks", "uordblks", "fordblks", "keepcost")]
info = ctypes.CDLL(None).mallinfo2
info.restype = Info
x = np.ones(6 << 20)  # 48 MiB
mapped = info().hblkhd
del x
print(mapped >> 20, info().fordblks >> 20)  # MiB in mappings of their own while it lives; MiB free in the heap after
"""
_USER_VARS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "GLIBC_TUNABLES")


def _probe(keep: bool, **extra: str) -> tuple[int, int]:
    env = {k: v for k, v in os.environ.items() if k not in _USER_VARS} | extra
    out = subprocess.run([sys.executable, "-c", _PROBE, "1" if keep else "0"], env=env, capture_output=True,
                         text=True, check=True)
    mapped, free = out.stdout.split()
    return int(mapped), int(free)


def _glibc_mallinfo2() -> bool:
    try:
        return sys.platform.startswith("linux") and hasattr(ctypes.CDLL(None), "mallinfo2")
    except OSError:
        return False


pytestmark = pytest.mark.skipif(not _glibc_mallinfo2(), reason="glibc 2.33 or later (mallopt, mallinfo2)")


def test_large_array_from_the_heap_and_kept_there():
    mapped, free = _probe(True)
    assert mapped < 48 and free >= 48, (mapped, free)
    # the check can fail: by default the same array has a mapping of its own, returned to the system when freed
    mapped, free = _probe(False)
    assert mapped >= 48 and free < 48, (mapped, free)


def test_user_malloc_settings_are_kept():
    mapped, free = _probe(True, MALLOC_TRIM_THRESHOLD_="131072")
    assert mapped >= 48 and free < 48, (mapped, free)


_AFTER_A_FIT = r"""
import ctypes, sys
import numpy as np
from mocapskel import pipeline
from mocapskel.synth.chains import hang_chain
take = hang_chain((3, 3, 3), 200, rng=np.random.default_rng(0), link_length=300.0, noise=0.5)
pipeline.run_until(take.markers, "clean")  # any entry point of the pipeline sets the allocator
class Info(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                 "fsmblks", "uordblks", "fordblks", "keepcost")]
info = ctypes.CDLL(None).mallinfo2
info.restype = Info
before = info().hblkhd
x = np.ones(6 << 20)
print((info().hblkhd - before) >> 20)
"""


def test_the_pipelines_entry_points_set_it():
    env = {k: v for k, v in os.environ.items() if k not in _USER_VARS}
    out = subprocess.run([sys.executable, "-c", _AFTER_A_FIT], env=env, capture_output=True, text=True, check=True)
    assert int(out.stdout.strip().splitlines()[-1]) < 48, out.stdout  # the 48 MiB array came from the heap
