"""hsiffc.batch.memory: after reuse_freed_memory, a large array freed by one frame is reused by the
next without fresh pages from the kernel (each check in a fresh process: the setting is
process-wide and is not undone)."""

from __future__ import annotations

import json
import platform
import subprocess
import sys

import pytest

from hsiffc.batch.memory import reuse_freed_memory

glibc = pytest.mark.skipif(platform.system() != "Linux" or platform.libc_ver()[0] != "glibc",
                           reason="the allocator settings exist on glibc (Linux) only")

_CHILD = """
import json, resource, sys
import numpy as np
from hsiffc.batch.memory import reuse_freed_memory
applied = reuse_freed_memory() if sys.argv[1] == "tuned" else None
faults = []
for _ in range(4):  # a 72 MB cube per 'frame', as a 2048 x 1088 x 8 float32 cube
    before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
    cube = np.empty((1088, 2048, 8), np.float32)
    cube.fill(1.0)
    faults.append(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
    del cube
print(json.dumps({"applied": applied, "faults": faults}))
"""


def _child(mode):
    out = subprocess.run([sys.executable, "-c", _CHILD, mode], capture_output=True, text=True,
                         check=True, timeout=120)
    return json.loads(out.stdout)


@glibc
def test_a_freed_cube_is_reused_without_new_pages_only_with_the_setting():
    default, tuned = _child("default"), _child("tuned")
    assert tuned["applied"] is True
    # without the setting every cube is mapped afresh (pages faulted in, zeroed by the kernel)
    assert min(default["faults"][1:]) > 0, default
    # with it, the cubes after the first reuse the first one's memory
    assert max(tuned["faults"][1:]) == 0, tuned


@glibc
def test_the_setting_is_applied_once_and_reported():
    assert reuse_freed_memory() is True
    assert reuse_freed_memory() is True  # the same values again: nothing to do


@pytest.mark.parametrize("kwargs", [{"largest_mb": 0}, {"largest_mb": 4096}, {"keep_mb": -1}])
def test_out_of_range_sizes_name_the_parameter(kwargs):
    with pytest.raises(ValueError, match=next(iter(kwargs))):
        reuse_freed_memory(**kwargs)
