"""The correction on an NVIDIA GPU (optional extra ``hsiffc[gpu]``).

``Pipeline.to("cuda")`` returns a :class:`~hsiffc.gpu.pipeline.GpuPipeline` for a fitted
pipeline of ``dark``, ``alpha_mask`` (paper alpha, DQ) and optionally ``model_ffc`` or
``two_point_ffc`` and ``reconstruct`` (nearest, bilinear or PPID at full resolution,
optionally with the spectral correction matrix, e.g. IMEC's); ``hsiffc correct --device
cuda`` runs a batch through it. Its
``transform`` gives the same frame as the CPU pipeline (within the float32 tolerance stated in
:mod:`hsiffc.gpu.kernels`); its ``stream`` overlaps upload, compute and download for live
frames. Stages it does not run on the device are refused with one line naming the step.

Toolchain: numba-cuda. The GPU kernels call the very scalar functions the CPU kernels are
built from (:func:`hsiffc.kernels.inversion.invert_point`,
:func:`hsiffc.kernels.modelffc.correct_point`, :func:`hsiffc.kernels.leakage.alpha_paper_point`
...): numba compiles one Python source for both targets, so there is no second copy of the
physics, and numba's CUDA simulator (``NUMBA_ENABLE_CUDASIM=1``) runs the same kernels on the
CPU, which is how CI tests them without a GPU. Where the CPU kernels work on whole rows (the
interpolation, the PPI, the band levels), the GPU kernels take the same terms in the same
order per value, and the tests hold them equal to the CPU's in the simulator. CuPy (present on the GPU machine) would need the
model rewritten in CUDA C. See ``docs/guide/gpu.md`` for what runs where and
``docs/results/gpu.md`` for the measurements.

Without numba-cuda or a GPU :func:`require` raises :class:`GpuUnavailableError` with one line
saying what is missing.
"""

from __future__ import annotations

import os

import numpy as np

from ..errors import HsiffcError

__all__ = ["DEVICES", "GpuUnavailableError", "available", "cuda_module", "require", "to_device"]

DEVICES = ("cpu", "cuda")
INSTALL = "install the extra with: pip install 'hsiffc[gpu]' (numba-cuda and the CUDA toolkit)"


class GpuUnavailableError(HsiffcError, RuntimeError):
    """The GPU path was asked for but cannot run here (module or device missing)."""


def simulated() -> bool:
    """True when numba's CUDA simulator is on (``NUMBA_ENABLE_CUDASIM=1``): kernels run on
    the CPU, for tests."""
    return os.environ.get("NUMBA_ENABLE_CUDASIM", "0") not in ("", "0")


_STATE: dict = {}


def cuda_module():
    """``numba.cuda``, imported once. numba-cuda (up to 0.30.4 at least) registers an
    overload of ``np.row_stack``, which numpy 2.5 removed: where numpy has no such name it
    is given numpy's own ``vstack`` (what ``row_stack`` always was) before the import."""
    if "cuda" in _STATE:
        return _STATE["cuda"]
    if not hasattr(np, "row_stack"):
        np.row_stack = np.vstack
    try:
        from numba import cuda
    except Exception as exc:  # noqa: BLE001 - any import failure means "not available"
        _STATE["cuda"] = None
        _STATE["why"] = f"numba.cuda cannot be imported ({type(exc).__name__}: {exc})"
        return None
    _STATE["cuda"] = cuda
    return cuda


def why_unavailable() -> str | None:
    """None when the GPU path can run, else one line saying what is missing."""
    if "ok" in _STATE:
        return _STATE["ok"]
    cuda = cuda_module()
    if cuda is None:
        why = _STATE["why"] + "; " + INSTALL
    elif simulated():
        why = None
    else:
        try:
            ok = cuda.is_available()
        except Exception as exc:  # noqa: BLE001
            ok, detail = False, f"{type(exc).__name__}: {exc}".splitlines()[0]
        else:
            detail = "no CUDA driver or NVIDIA GPU was found"
        why = None if ok else (f"no usable NVIDIA GPU: {detail}; run with --device cpu, or "
                               "on a machine with an NVIDIA GPU and its driver")
    _STATE["ok"] = why
    return why


def available() -> bool:
    """True when the GPU path can run (numba-cuda imports and a device, or the simulator)."""
    return why_unavailable() is None


def require(what: str = "--device cuda") -> None:
    """Raise :class:`GpuUnavailableError` (one line) unless the GPU path can run."""
    why = why_unavailable()
    if why is not None:
        raise GpuUnavailableError(f"{what}: {why}")


def to_device(pipeline, device: str):
    """``pipeline`` for ``device``: itself for "cpu", a :class:`GpuPipeline` for "cuda"."""
    if device not in DEVICES:
        from ..errors import ParameterError
        raise ParameterError(f"device={device!r}: use one of {', '.join(DEVICES)}")
    if device == "cpu":
        return pipeline
    require(f"device={device!r}")
    from .pipeline import GpuPipeline
    return GpuPipeline(pipeline)
