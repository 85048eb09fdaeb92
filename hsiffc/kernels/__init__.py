"""Compiled (numba) kernels behind the array functions.

Each kernel *is* the implementation of a public function elsewhere (e.g.
:func:`hsiffc.leakage.model.response` validates and broadcasts its arguments, then calls
:func:`hsiffc.kernels.leakage.response_kernel`); there is no second, pure-numpy copy.

Compilation: ``cache=True`` stores the machine code next to this package (or in numba's user
cache when that is not writable), so only the first call on a machine compiles (measured by
``benchmarks/bench_kernels.py``). ``fastmath`` is off: results follow IEEE 754.
"""

import os as _os

#: numba's OpenMP threads (GNU libgomp) spin after every parallel region unless told to wait
#: passively: on a machine whose cores other processes share, a spinning thread takes a core
#: from the serial code between kernels and from the thread the region waits for. Measured
#: here (2 cores, load 17-21): 40 calls of the photon transfer's pair statistics on a
#: 544 x 1024 frame pair took 2.95 s wall and 0.50-0.59 s CPU spinning, 0.10-0.35 s wall and
#: 0.05 s CPU waiting passively. So hsiffc asks for passive waiting unless the environment
#: already sets OMP_WAIT_POLICY; it takes effect when numba starts its threads (the first
#: parallel kernel of the process), so a process that ran one before importing hsiffc keeps
#: its policy.
_os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
