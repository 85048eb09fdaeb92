"""Compiled (numba) kernels behind the array functions.

Each kernel *is* the implementation of a public function elsewhere (e.g.
:func:`hsiffc.leakage.model.response` validates and broadcasts its arguments, then calls
:func:`hsiffc.kernels.leakage.response_kernel`); there is no second, pure-numpy copy.

Compilation: ``cache=True`` stores the machine code next to this package (or in numba's user
cache when that is not writable), so only the first call on a machine compiles (measured by
``benchmarks/bench_kernels.py``). ``fastmath`` is off: results follow IEEE 754.
"""
