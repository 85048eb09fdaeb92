"""Planning a batch: inputs (files, folders, globs) to jobs, one output name per input.

>>> output_name("day1/cube_07.tif")
'day1/cube_07.corrected.tif'
"""

from __future__ import annotations

import glob
import os
import re
from dataclasses import dataclass
from pathlib import Path, PurePath

from ..errors import HsiffcError
from ..io.corrected import SUFFIX
from ..io import IMAGE_SUFFIXES

__all__ = ["BatchError", "Job", "REFLECTANCE_SUFFIX", "check_formats", "discover_inputs",
           "is_batch_output",
           "output_name", "output_suffix", "plan_jobs", "unread_files"]

_MAGIC = re.compile(r"[*?[]")


class BatchError(HsiffcError):
    """The batch cannot start (bad arguments, inputs or options): a usage error."""



def _is_tiff(path) -> bool:
    """An image file hsiffc reads (TIFF, PNG, ENVI header, FITS)."""
    return PurePath(path).suffix.lower() in IMAGE_SUFFIXES


#: the name of a reflectance product (a pipeline with a reflectance stage): it says what it holds
REFLECTANCE_SUFFIX = ".reflectance.tif"
_SUFFIXES = (SUFFIX, REFLECTANCE_SUFFIX)
#: the cubes ``hsiffc correct --format envi|ome|netcdf`` writes beside a corrected file
_ENVI_OUTPUT = re.compile("(" + "|".join(re.escape(s[:-len(".tif")]) for s in _SUFFIXES) + ")"
                          + r"(_f\d{4,})?((\.dq|\.alpha)?\.(hdr|img)|\.ome\.tiff?|\.nc)$")


def check_formats(formats) -> tuple[str, ...]:
    """``formats`` (a name, a comma-separated list or a sequence) as a tuple of distinct
    product formats, in :data:`PRODUCT_FORMATS` order.

    >>> check_formats("envi"), check_formats("netcdf,tiff")
    (('envi',), ('tiff', 'netcdf'))
    """
    from ..cubes.stream import PRODUCT_FORMATS

    items = formats.split(",") if isinstance(formats, str) else list(formats or ())
    names = [str(f).strip().lower() for f in items if str(f).strip()]
    bad = [f for f in names if f not in PRODUCT_FORMATS]
    if bad or not names:
        raise BatchError(f"--format must be one or more of {', '.join(PRODUCT_FORMATS)} "
                         f"(comma-separated, e.g. envi or envi,tiff), got "
                         f"{formats if not isinstance(formats, str) else repr(formats)}")
    return tuple(f for f in PRODUCT_FORMATS if f in names)


def output_suffix(steps) -> str:
    """The suffix of a batch's outputs: ``.reflectance.tif`` when a step of the pipeline
    (``steps``: dicts with ``"stage"``) is the reflectance stage, else ``.corrected.tif``.

    >>> output_suffix([{"stage": "dark"}, {"stage": "reflectance"}, {"stage": "reconstruct"}])
    '.reflectance.tif'
    >>> output_suffix([{"stage": "dark"}])
    '.corrected.tif'
    """
    return REFLECTANCE_SUFFIX if any(s.get("stage") == "reflectance" for s in steps) else SUFFIX


def is_batch_output(path) -> bool:
    """Whether ``path`` is named like an output of ``hsiffc correct``: a corrected file
    (``*.corrected.tif``, a reflectance product ``*.reflectance.tif``) or one of its cubes
    (``*.corrected.hdr``, ``*.corrected_f0001.dq.img``, ``*.reflectance.nc``, ...).

    >>> is_batch_output("a.corrected.tif"), is_batch_output("a.corrected_f0002.dq.hdr")
    (True, True)
    >>> is_batch_output("a.corrected_f0001.ome.tif"), is_batch_output("a.corrected.alpha.img")
    (True, True)
    >>> is_batch_output("a.corrected_f10000.dq.img")  # a file of more than 10,000 frames
    True
    >>> is_batch_output("a.reflectance.tif"), is_batch_output("a.reflectance.dq.hdr")
    (True, True)
    >>> is_batch_output("a.tif")
    False
    """
    name = PurePath(path).name.lower()
    return name.endswith(_SUFFIXES) or name.endswith(tuple(s + "f" for s in _SUFFIXES)) or \
        bool(_ENVI_OUTPUT.search(name))


def _hidden(rel: PurePath) -> bool:
    return any(part.startswith(".") for part in rel.parts)


def discover_inputs(args) -> tuple[list[tuple[Path, PurePath]], list[Path]]:
    """Expand files, folders and globs into ``(path, relative name)`` pairs.

    Folders are searched recursively for ``*.tif``/``*.tiff`` (hidden entries skipped) and
    globs (``*``, ``?``, ``[...]``, ``**``) are expanded; their relative name is the path below
    the folder or below the glob's fixed leading part. A file named directly keeps its name.
    Files named like outputs of this command (``*.corrected.tif`` and their ENVI cubes, see
    :func:`is_batch_output`) found by a folder or a glob are ignored (returned as the second
    list). Duplicates are dropped.

    Raises
    ------
    BatchError
        An argument that does not exist, a glob or folder without TIFF files, or a file that
        is not a ``.tif``/``.tiff``.
    """
    found: dict[Path, tuple[Path, PurePath]] = {}
    ignored: list[Path] = []

    def add(path: Path, rel: PurePath):
        key = path.resolve()
        if key not in found:
            found[key] = (path, rel)

    for arg in args:
        text = os.fspath(arg)
        if _MAGIC.search(text) and not Path(text).exists():
            root = _glob_root(text)
            files = [Path(m) for m in sorted(glob.glob(text, recursive=True))
                     if Path(m).is_file() and _is_tiff(m)]
            if not files:
                raise BatchError(f"{text}: the pattern matches no TIFF or other image file "
                                 "(.tif/.tiff, .png, .hdr, .fits)")
            for f in files:
                rel = PurePath(os.path.relpath(f, root)) if root else PurePath(f)
                if rel.parts and rel.parts[0] == "..":
                    rel = PurePath(f.name)
                if is_batch_output(f):
                    ignored.append(f)
                else:
                    add(f, rel)
            continue
        path = Path(text)
        if path.is_dir():
            files = sorted(q for q in path.rglob("*")
                           if q.is_file() and _is_tiff(q) and not _hidden(q.relative_to(path)))
            if not files:
                raise BatchError(f"{path}: the folder holds no TIFF or other image file "
                                 "(.tif/.tiff, .png, .hdr, .fits)")
            for f in files:
                if is_batch_output(f):
                    ignored.append(f)
                else:
                    add(f, f.relative_to(path))
        elif path.is_file():
            if not _is_tiff(path):
                raise BatchError(f"{path}: not a TIFF file name (.tif/.tiff) nor another image "
                                 "format hsiffc correct reads (.png, .hdr, .fits)")
            add(path, PurePath(path.name))
        elif path.exists():
            raise BatchError(f"{path}: neither a regular file nor a folder")
        else:
            raise BatchError(f"{path}: no such file or folder")
    return list(found.values()), ignored


#: files beside the images that hsiffc reads with them: sidecars and ENVI data files
_COMPANIONS = {"hsiffc.toml"}


def unread_files(args) -> list[Path]:
    """The files in the folders among ``args`` that the batch does not read: neither an
    image hsiffc reads, nor an output of ``hsiffc correct``, a sidecar (``hsiffc.toml``) or the
    data file of an ENVI header (``NAME.img``/``.raw``/``.dat``/no suffix beside
    ``NAME.hdr``); hidden entries are not searched. Listed in the summary, so that a ``.jpg``
    or ``.txt`` that was meant as an input is not skipped without a word.

    >>> unread_files([])
    []
    """
    out = []
    for arg in args:
        path = Path(os.fspath(arg))
        if not path.is_dir():
            continue
        for f in sorted(path.rglob("*")):
            if (not f.is_file() or _hidden(f.relative_to(path)) or _is_tiff(f)
                    or is_batch_output(f) or f.name in _COMPANIONS
                    or f.with_suffix(".hdr").is_file()):
                continue
            out.append(f)
    return out


def _glob_root(pattern: str) -> str:
    parts = PurePath(pattern).parts
    fixed = []
    for part in parts[:-1]:
        if _MAGIC.search(part):
            break
        fixed.append(part)
    return str(PurePath(*fixed)) if fixed else ""


def output_name(rel, suffix: str = SUFFIX) -> str:
    """The output's name below OUTDIR for an input's relative name (POSIX separators);
    ``suffix`` as :func:`output_suffix` gives it."""
    rel = PurePath(rel)
    return rel.with_name(rel.stem + suffix).as_posix()


@dataclass(frozen=True)
class Job:
    """One input file and where its output goes (absolute paths)."""

    input: str
    rel: str
    output: str


def plan_jobs(inputs, outdir, suffix: str = SUFFIX) -> tuple[list[Job], list[Path]]:
    """Jobs for ``inputs`` (files, folders, globs) writing below ``outdir``, each output
    named with ``suffix`` (:func:`output_suffix`).

    Raises BatchError if two inputs map to one output or an output would overwrite an input.
    """
    outdir = Path(outdir)
    if outdir.exists() and not outdir.is_dir():
        raise BatchError(f"{outdir}: the output folder is a file; give a folder (-o OUTDIR)")
    pairs, ignored = discover_inputs(inputs)
    if not pairs:
        raise BatchError("no input files; give TIFF files, folders or globs")
    jobs, seen = [], {}
    inputs_resolved = {p.resolve() for p, _ in pairs}
    inodes = {_inode(p) for p, _ in pairs} - {None}
    root = outdir.resolve()
    for path, rel in pairs:
        out = root / output_name(rel, suffix)  # not resolved: a link at the name is never followed
        if out in seen:
            raise BatchError(f"{path} and {seen[out]} would both be written to {out}; give them "
                             "from their folder (their relative paths keep them apart) or "
                             "correct them in separate runs")
        seen[out] = path
        if out.resolve() in inputs_resolved or (out.exists() and _inode(out) in inodes):
            raise BatchError(f"the output for {path} would overwrite the input {out}; hsiffc "
                             "correct never writes over an input: choose another output folder "
                             "(-o) or move that input")
        jobs.append(Job(str(path.resolve()), PurePath(rel).as_posix(), str(out)))
    return jobs, ignored


def _inode(path: Path):
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_dev, st.st_ino)


