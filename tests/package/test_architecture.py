"""The layers of docs/architecture.md hold in the code: a folder imports only folders of its
own layer or below (every import statement counts, those inside functions too)."""

from __future__ import annotations

import ast
import functools
import re
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
PACKAGE = REPO / "hsiffc"
PAGE = REPO / "docs" / "architecture.md"


def layers() -> list[set[str]]:
    """The layer table of the architecture page, bottom layer first."""
    block = re.search(r"<!-- layers -->\s*```text\n(.*?)```", PAGE.read_text(), re.S)
    assert block, f"{PAGE} has no layer table (a ```text block after <!-- layers -->)"
    rows = []
    for line in block.group(1).splitlines():
        m = re.match(r"\s*(\d+)\s+(.*?)\s{2,}", line + "  ")
        if m:
            rows.append((int(m.group(1)), set(m.group(2).split())))
    rows.sort()
    return [names for _, names in rows]


def unit(module: str) -> str:
    """The folder (or top-level module) a dotted hsiffc module belongs to."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else "hsiffc"


@functools.lru_cache(maxsize=None)
def _import_statements(path: Path, stamp: tuple) -> tuple:
    """The import statements of a source file, parsed once per test process for a given
    ``stamp`` (modification time and size): several checks walk the same files."""
    tree = ast.parse(path.read_text(encoding="utf-8"), str(path))
    return tuple(n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom)))


def import_statements(path: Path) -> tuple:
    """``ast.Import`` and ``ast.ImportFrom`` nodes of ``path`` (see :func:`_import_statements`)."""
    st = path.stat()
    return _import_statements(path, (st.st_mtime_ns, st.st_size))


def module_imports():
    """(importing module, the module an import statement names, the names it imports, path,
    line) for every import statement of the package."""
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(REPO).with_suffix("").parts
        is_pkg = rel[-1] == "__init__"
        module = ".".join(rel[:-1] if is_pkg else rel)
        for node in import_statements(path):
            if isinstance(node, ast.ImportFrom):
                if node.level:
                    base = module.split(".") if is_pkg else module.split(".")[:-1]
                    base = base[: len(base) - (node.level - 1)]
                    target = ".".join(base + ([node.module] if node.module else []))
                else:
                    target = node.module or ""
                yield module, target, [a.name for a in node.names], path, node.lineno
            elif isinstance(node, ast.Import):
                for a in node.names:
                    yield module, a.name, [], path, node.lineno


def imports() -> list[tuple[str, str, str]]:
    """(importing unit, imported unit, where) for every hsiffc import in the package."""
    found = []
    for module, target, names, path, line in module_imports():
        targets = [f"hsiffc.{n}" for n in names] if target == "hsiffc" else [target]
        for t in targets:
            if t.startswith("hsiffc."):
                found.append((unit(module), unit(t), f"{path.relative_to(REPO)}:{line}"))
    return found


def test_every_folder_of_the_package_is_in_the_layer_table():
    table = set().union(*layers())
    units = {p.name if p.is_dir() else p.stem for p in PACKAGE.iterdir()
             if (p.is_dir() and (p / "__init__.py").exists()) or p.suffix == ".py"}
    units -= {"__init__", "py"}
    assert units - table == set(), f"add these to the layer table of {PAGE.name}"
    assert table - units == set(), f"the layer table of {PAGE.name} names what is not there"


#: the upward imports the architecture page names, each with its reason
EXCEPTIONS = {("data", "cubes", "hsiffc/data/frame.py"):
              "Frame.to_xarray() converts a cube in hand (imported when called)",
              ("io", "cubes", "hsiffc/io/__init__.py"):
              "hsiffc.io.write_cube, the input and output face, calls the cube writers (imported "
              "when called); cubes read and write through io"}


def test_no_layer_imports_a_layer_above_it():
    level = {name: i for i, names in enumerate(layers()) for name in names}
    level["__version__"] = -1  # the package's version string
    level["hsiffc"] = len(level)  # the package's face
    upward = [f"{where}: {a} (layer {level[a]}) imports {b} "
              f"(layer {level.get(b, 'not in the table')})"
              for a, b, where in imports()
              if a != b and level.get(b, 99) > level.get(a, -1)
              and (a, b, where.split(":")[0]) not in EXCEPTIONS]
    assert not upward, "\n".join(upward)


def _cycles(edges) -> list[list[str]]:
    """The strongly connected components of more than one node of a directed graph
    (``edges``: node -> set of nodes), each sorted (Tarjan's algorithm)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            part = []
            while True:
                w = stack.pop()
                on.discard(w)
                part.append(w)
                if w == v:
                    break
            if len(part) > 1:
                out.append(sorted(part))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return out


def test_no_folders_import_each_other():
    """No cycle of folders, however long, counting imports inside functions; the upward
    imports the page names (:data:`EXCEPTIONS`) are left out, each with its reason."""
    edges: dict[str, set] = {}
    where: dict[tuple, str] = {}
    for a, b, at in imports():
        if a != b and (a, b, at.split(":")[0]) not in EXCEPTIONS:
            edges.setdefault(a, set()).add(b)
            where.setdefault((a, b), at)
    found = _cycles(edges)
    assert not found, "\n".join(
        " <-> ".join(c) + ": " + ", ".join(w for (a, b), w in where.items() if {a, b} <= set(c))
        for c in found)


def test_the_cycle_check_sees_a_long_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


#: module cycles inside a folder still to break, each with what is left to do
MODULE_CYCLES = {
    ("hsiffc.cubes.product", "hsiffc.cubes.xr"): "Cube.to_xarray and to_xarray's Cube.from_frame",
    ("hsiffc.io._readers", "hsiffc.io.emva", "hsiffc.io.source", "hsiffc.io.tiff"):
        "a format's reader opens the frame source for its own files (open_layout dispatches "
        "to them, the source reads through open_layout)",
}


def test_no_modules_import_each_other():
    """No cycle of modules (imports inside functions count), but those listed in
    :data:`MODULE_CYCLES`."""
    edges: dict[str, set] = {}
    for module, target, names, _, _ in module_imports():
        for t in [target] + [f"{target}.{n}" for n in names]:
            where = REPO.joinpath(*t.split("."))
            if t.startswith("hsiffc") and t != module and (
                    where.with_suffix(".py").exists() or (where / "__init__.py").exists()):
                edges.setdefault(module, set()).add(t)
    # a package imports its modules to show them on its face: the face is not a cycle; nor
    # are the upward imports the page names (module -> the folder it imports)
    named = {(path.replace("/", ".")[:-3], f"hsiffc.{b}") for _, b, path in EXCEPTIONS}

    def kept(m, t):
        return not m.startswith(t + ".") and not any(
            m == mod and (t == up or t.startswith(up + ".")) for mod, up in named)

    found = [c for c in _cycles({m: {t for t in ts if kept(m, t)} for m, ts in edges.items()})
             if tuple(c) not in MODULE_CYCLES]
    assert not found, found


def test_the_check_sees_an_upward_import(tmp_path, monkeypatch):
    # the check itself can fail: a data-model module importing the CLI is caught
    fake = tmp_path / "hsiffc" / "data"
    fake.mkdir(parents=True)
    (fake / "x.py").write_text("from ..cli import main\n")
    here = sys.modules[__name__]
    monkeypatch.setattr(here, "PACKAGE", tmp_path / "hsiffc")
    monkeypatch.setattr(here, "REPO", tmp_path)
    found = imports()
    assert ("data", "cli", "hsiffc/data/x.py:1") in found


@pytest.mark.parametrize("old, new", [("hsiffc.frame", "hsiffc.data.frame"),
                                      ("hsiffc.model_ffc", "hsiffc.flatfield.model_based"),
                                      ("hsiffc.io.metadata", "hsiffc.io._metadata"),
                                      ("hsiffc.calibrate.pixelfit", "hsiffc.kernels.pixelfit")])
def test_moved_modules_keep_their_old_import_path(old, new):
    import importlib

    sys.modules.pop(old, None)
    with pytest.warns(DeprecationWarning, match=new.replace(".", r"\.")):
        moved = importlib.import_module(old)
    assert moved is importlib.import_module(new)


#: io modules merged into the module of their format, with names their old path exported
MERGED_IO = {"hsiffc.io.corrected_format": ("hsiffc.io.corrected", ["FORMAT", "PLANE_DTYPES"]),
             "hsiffc.io.corrected_writer": ("hsiffc.io.corrected", ["CorrectedWriter"]),
             "hsiffc.io.envi_write": ("hsiffc.io.envi", ["write_envi"]),
             "hsiffc.io.emva_descriptor": ("hsiffc.io.emva", ["parse_descriptor"]),
             "hsiffc.io.sourcefacts": ("hsiffc.io.source", ["resolve_facts", "read_stored"]),
             "hsiffc.io.tiffpages": ("hsiffc.io.tiff", ["open_tiff", "CORRECTED_MARK"]),
             "hsiffc.io.document": ("hsiffc.io.tiff", ["parse_document", "MINIMAL_DOCUMENT"])}


@pytest.mark.parametrize("old", sorted(MERGED_IO))
def test_merged_io_modules_keep_their_old_import_path_and_names(old):
    import importlib

    new, names = MERGED_IO[old]
    sys.modules.pop(old, None)
    with pytest.warns(DeprecationWarning, match=new.replace(".", r"\.")):
        moved = importlib.import_module(old)
    assert moved is importlib.import_module(new)
    assert not (PACKAGE / "io" / f"{old.rsplit('.', 1)[1]}.py").exists()
    assert [n for n in names if not hasattr(moved, n)] == []


#: what a command or an import must not load: numba's compiler (with llvmlite), scipy and the
#: compiled code (they load when a command that computes runs)
HEAVY = ("numba", "llvmlite", "scipy", "hsiffc.kernels", "hsiffc.calibrate")


@pytest.mark.parametrize("code", [
    "import hsiffc.stages",
    "import runpy, sys\nsys.argv = ['hsiffc', '--version']\ntry:\n"
    "    runpy.run_module('hsiffc', run_name='__main__')\nexcept SystemExit:\n    pass",
], ids=["import hsiffc.stages", "hsiffc --version"])
def test_imports_and_the_version_load_no_compiler(code):
    import json
    import subprocess

    code += f"\nimport json\nprint(json.dumps([m for m in {HEAVY!r} if m in sys.modules]))"
    run = subprocess.run([sys.executable, "-c", "import sys\n" + code], capture_output=True,
                         text=True, timeout=120)
    assert run.returncode == 0, run.stderr[-2000:]
    assert json.loads(run.stdout.splitlines()[-1]) == []


def private_imports(paths, own: set[str]):
    """(path, line, names) of every import of a ``_``-prefixed name (not a dunder) from a module
    of this project (a top-level name of ``own``, such as ``hsiffc`` or ``test_spectral``, or a
    relative import), and of a ``_``-prefixed module of another folder of the package (a
    relative import going up, or ``hsiffc.FOLDER._module`` from outside FOLDER). A folder's
    own private modules are its internals; tests may import a private module to test it."""
    for path in paths:
        in_package = PACKAGE in path.parents
        folder = path.parent.relative_to(PACKAGE).parts[:1] if in_package else ()
        for node in import_statements(path):
            if isinstance(node, ast.ImportFrom):
                parts = [p for p in (node.module or "").split(".") if p]
                if node.level == 0 and (parts or [""])[0] not in own:
                    continue
                private = [a.name for a in node.names if _private(a.name)]
                crosses = (node.level >= 2 if node.level else
                           parts[0] == "hsiffc" and tuple(parts[1:2]) != folder)
                if in_package and crosses:
                    private += [p for p in parts if _private(p)]
            elif isinstance(node, ast.Import) and in_package:
                private = [p for a in node.names if a.name.startswith("hsiffc.")
                           for p in a.name.split(".") if _private(p)]
            else:
                continue
            if private:
                yield path, node.lineno, ", ".join(private)


def _private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def test_no_module_imports_a_private_name_of_another():
    """One rule for the package and its tests: what another module may use is public; a
    shared test helper lives in a public module (``tests/checks.py``, ``tests/testfiles.py``),
    so a test module also runs alone (pytest puts only its own folder on the path)."""
    tests = REPO / "tests"
    own = {"hsiffc"} | {p.stem for p in tests.rglob("*.py")}
    found = list(private_imports(sorted(PACKAGE.rglob("*.py")) + sorted(tests.rglob("*.py")),
                                 own))
    assert not found, "private names imported across modules:\n" + "\n".join(
        f"  {path.relative_to(REPO)}:{line}: {names}" for path, line, names in found)


def test_the_private_import_check_sees_one(tmp_path):
    bad = tmp_path / "test_x.py"
    bad.write_text("def f():\n    from test_spectral import _xml\n")
    ok = tmp_path / "test_y.py"
    ok.write_text("from testfiles import synthetic_imec_xml\nfrom os import _exit\n"
                  "from hsiffc.io._metadata import parse_mosaic\n")
    found = list(private_imports([bad, ok], {"test_spectral", "testfiles", "hsiffc"}))
    assert [(line, names) for _, line, names in found] == [(2, "_xml")]
    io, batch = PACKAGE / "io" / "source.py", PACKAGE / "batch" / "task.py"
    assert [names for _, _, names in private_imports([io, batch], {"hsiffc"})] == []
