"""Dr.Jit maps NumPy inputs without copying and its LLVM kernels read the last packet
whole, up to 120 bytes past an array's end: :func:`avsm_dr._arrays.aligned` leaves
``TAIL_PAD`` readable bytes after the data.  Without them, ``python -m experiments frame
--quick`` after the memory benchmark (which sets glibc's mmap threshold to 64 KiB, so a
large buffer ends at an unmapped page) segfaulted in the DSM build."""
import subprocess
import sys
from pathlib import Path

import numpy as np

from avsm_dr import _arrays as A


def test_aligned_leaves_a_readable_tail():
    for n in (1, 7, 9200, 70001):
        for dt in (np.uint8, np.uint32, np.float64):
            out = A.aligned(np.arange(n) % 7, dt)
            assert out.ctypes.data % 64 == 0 and A._has_tail(out)
            assert A.aligned(out) is out                         # already padded: no copy
            np.testing.assert_array_equal(out, np.arange(n) % 7)
    bare = np.empty(1024 + 8)                                    # 64-aligned view without a tail
    start = (-bare.ctypes.data % 64) // 8
    view = bare[start:start + 1024]
    if view.size == 1024:
        assert A.aligned(view) is not view



# ------------------------------------------------ the crash this padding fixed
# With glibc serving every buffer >= 64 KiB by its own mmap (as the memory benchmark's
# mallopt makes it), a buffer without tail padding ends on an unmapped page, and the frame
# study's DSM build segfaulted on the kernels' last packet load (the random-order crash of
# the test suite, seed 2026, after test_experiments[bench]).  In a subprocess: the crash is
# the failure.
ROOT = Path(__file__).resolve().parents[1]

SCRIPT = """
import ctypes, sys, tempfile
import avsm_dr
libc = ctypes.CDLL("libc.so.6")
libc.mallopt(-3, 1 << 16)      # M_MMAP_THRESHOLD: every buffer >= 64 KiB its own mapping
libc.mallopt(-1, 1 << 16)      # M_TRIM_THRESHOLD
import dataclasses
from experiments import frame
# the plume at 128^2 is where the unpadded build crashed (3 of 3 runs with TAIL_PAD = 0, in
# 2.5 s; the whole quick frame study took 70 s to pass); every other cell adds only time
study = dataclasses.replace(frame.STUDY, quick=dict(frame.QUICK, scenes=["plume"], resolutions=[128]))
study.run(quick=True, out=tempfile.mkdtemp())
"""


def test_frame_study_survives_page_ending_buffers():
    r = subprocess.run([sys.executable, "-c", SCRIPT], cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, (r.returncode, r.stderr[-2000:])
