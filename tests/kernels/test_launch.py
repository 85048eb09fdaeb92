"""One stale-cache mechanism for every compiled CPU kernel: each build cached on disk is named by
a digest of the sources it can compile in, computed on the first build, not at import."""

from __future__ import annotations

import importlib
import importlib.util
import json
import pkgutil
import shutil
import subprocess
import sys
from pathlib import Path

import hsiffc.kernels
from hsiffc.kernels import launch

KERNELS = Path(hsiffc.kernels.__file__).resolve().parent


def _kernel_modules():
    return [importlib.import_module(f"hsiffc.kernels.{m.name}")
            for m in pkgutil.iter_modules([str(KERNELS)])]


def _digest_of_copy(root: Path) -> str:
    """source_digest() of a copy of launch.py in ``root``/hsiffc/kernels (it hashes its own
    folder and ../data/dq.py)."""
    spec = importlib.util.spec_from_file_location("launch_copy",
                                                  root / "hsiffc" / "kernels" / "launch.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module.source_digest()


def test_the_digest_changes_when_any_source_a_kernel_compiles_in_changes(tmp_path):
    shutil.copytree(KERNELS, tmp_path / "hsiffc" / "kernels",
                    ignore=shutil.ignore_patterns("__pycache__"))
    (tmp_path / "hsiffc" / "data").mkdir()
    shutil.copy(KERNELS.parent / "data" / "dq.py", tmp_path / "hsiffc" / "data" / "dq.py")
    digest = _digest_of_copy(tmp_path)
    assert digest == launch.source_digest()  # the copy hashes the same sources
    seen = {digest}
    # the calibration's fit (moved from hsiffc/calibrate), a kernel, the DQ bits, a new file
    for name in ("kernels/lm.py", "kernels/pixelfit.py", "kernels/vmath.py", "data/dq.py"):
        path = tmp_path / "hsiffc" / name
        path.write_text(path.read_text() + "# edited\n")
        seen.add(_digest_of_copy(tmp_path))
    (tmp_path / "hsiffc" / "kernels" / "new.py").write_text("X = 1\n")
    seen.add(_digest_of_copy(tmp_path))
    assert len(seen) == 6  # every edit gives a new digest: every cached build compiles afresh


def test_every_build_cached_on_disk_is_named_by_the_digest():
    digest = launch.source_digest()
    cached, plain = [], []
    for module in _kernel_modules():
        for name, obj in vars(module).items():
            if isinstance(obj, launch.Kernel):
                builds = [obj.parallel, obj.serial]
            elif isinstance(obj, launch.CachedJit):
                builds = [obj.dispatcher]
            elif hasattr(obj, "py_func") and hasattr(obj, "_cache"):  # a plain numba dispatcher
                builds = [obj]
            else:
                continue
            for d in builds:
                # numba's NullCache where cache=False: compiled into the callers, never loaded
                on_disk = type(d._cache).__name__ != "NullCache"
                (cached if on_disk else plain).append((module.__name__, name, d.py_func.__name__))
    assert [c for c in cached if not c[2].endswith("_" + digest)] == []
    moved = {m for m, _, _ in cached}
    assert {"hsiffc.kernels.pixelfit", "hsiffc.kernels.pixelsamples",
            "hsiffc.kernels.sweepstats", "hsiffc.kernels.select"} <= moved
    assert any(m == "hsiffc.kernels.lm" for m, _, _ in plain)  # the fit's helpers: compiled in


def test_importing_the_compiled_code_builds_and_hashes_nothing():
    code = ("import json, pkgutil, importlib, hsiffc.kernels as k, hsiffc.calibrate\n"
            "mods = [importlib.import_module('hsiffc.kernels.' + m.name)\n"
            "        for m in pkgutil.iter_modules(k.__path__)]\n"
            "from hsiffc.kernels import launch\n"
            "built = [n for m in mods for n, o in vars(m).items()\n"
            "         if isinstance(o, launch.Kernel) and 'parallel' in vars(o)\n"
            "         or isinstance(o, launch.CachedJit) and 'dispatcher' in vars(o)]\n"
            "print(json.dumps([launch.source_digest.cache_info().currsize, built]))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    assert json.loads(run.stdout.splitlines()[-1]) == [0, []]
