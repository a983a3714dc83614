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
if sys.argv[1] == "keep":
    from mocapskel.solvers.allocator import keep_large_blocks
    keep_large_blocks()
elif sys.argv[1] == "fit":  # any entry point of the pipeline sets the allocator
    from mocapskel import pipeline
    from mocapskel.synth.chains import hang_chain
    take = hang_chain((3, 3, 3), 200, rng=np.random.default_rng(0), link_length=300.0, noise=0.5)
    pipeline.run_until(take.markers, "clean")
class Info(ctypes.Structure):
    _fields_ = [(n, ctypes.c_size_t) for n in ("arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks",
                                                 "fsmblks", "uordblks", "fordblks", "keepcost")]
info = ctypes.CDLL(None).mallinfo2
info.restype = Info
before = info().hblkhd
x = np.ones(6 << 20)  # 48 MiB
mapped = info().hblkhd - before
del x
print(mapped >> 20, info().fordblks >> 20)  # MiB in mappings of their own while it lives; MiB free in the heap after
"""
_USER_VARS = ("MALLOC_MMAP_THRESHOLD_", "MALLOC_TRIM_THRESHOLD_", "GLIBC_TUNABLES")


def _probe(mode: str, **extra: str) -> tuple[int, int]:
    """(MiB of a 48 MiB array in mappings of its own, MiB free in the heap after it is freed), in a fresh process:
    ``mode`` "keep" after keep_large_blocks, "fit" after a pipeline entry point, "none" with neither."""
    env = {k: v for k, v in os.environ.items() if k not in _USER_VARS} | extra
    out = subprocess.run([sys.executable, "-c", _PROBE, mode], env=env, capture_output=True, text=True, check=True)
    mapped, free = out.stdout.split()[-2:]
    return int(mapped), int(free)


def _glibc_mallinfo2() -> bool:
    try:
        return sys.platform.startswith("linux") and hasattr(ctypes.CDLL(None), "mallinfo2")
    except OSError:
        return False


pytestmark = pytest.mark.skipif(not _glibc_mallinfo2(), reason="glibc 2.33 or later (mallopt, mallinfo2)")


def test_large_array_from_the_heap_and_kept_there():
    mapped, free = _probe("keep")
    assert mapped < 48 and free >= 48, (mapped, free)
    # the check can fail: by default the same array has a mapping of its own, returned to the system when freed
    mapped, free = _probe("none")
    assert mapped >= 48 and free < 48, (mapped, free)


def test_user_malloc_settings_are_kept():
    mapped, free = _probe("keep", MALLOC_TRIM_THRESHOLD_="131072")
    assert mapped >= 48 and free < 48, (mapped, free)


def test_the_pipelines_entry_points_set_it():
    mapped, free = _probe("fit")
    assert mapped < 48, (mapped, free)  # the 48 MiB array came from the heap
