"""The product file base: one versioned ``.npz`` of arrays plus a JSON manifest, no pickle.

Calibrations and fitted pipelines are both products (Rubin's calibration products are the
model): a ``format`` name (the product type), a ``format_version`` (schema), the hsiffc version
that wrote it, named arrays and a JSON manifest stored as a uint8 array ``manifest.json``.
Files are written atomically (never replacing an existing file unless asked) and read with
``allow_pickle=False``: no code is ever executed from a product file. Each product validates
itself against the data it is applied to (e.g. :meth:`hsiffc.calibrate.Calibration.check_compatible`).
"""

from __future__ import annotations

import json
import zipfile
import zlib
from pathlib import Path

import numpy as np

from .. import __version__
from ..files.jsonsafe import json_safe
from ..files.atomic import atomic_path
from ..errors import DataFormatError, HsiffcError


MANIFEST = "manifest.json"


def write_product(path, *, format: str, format_version: int, manifest: dict, arrays: dict,
                  overwrite: bool = False) -> Path:
    """Write a product file atomically.

    Parameters
    ----------
    path : path-like, ending in ``.npz``
    format, format_version : str, int
        Product type and schema version, stored first in the manifest.
    manifest : dict
        Description: plain values, numpy scalars or arrays and paths (converted by
        :func:`hsiffc.files.jsonsafe.json_safe`; non-finite floats become null).
    arrays : dict of str to ndarray
        Names must not be ``manifest.json``.
    overwrite : bool
        Replace an existing file (else FileExistsError, the file left unchanged).
    """
    path = Path(path)
    if path.suffix != ".npz":
        raise ValueError(f"{format} files end in .npz, got {path.name!r}")
    head = {"format": format, "format_version": int(format_version),
            "hsiffc_version": __version__}
    text = json.dumps(json_safe({**head, **manifest}, strict=True, what=f"the {format} manifest"),
                      indent=1).encode()
    payload = {k: np.ascontiguousarray(v) for k, v in arrays.items()}
    payload[MANIFEST] = np.frombuffer(text, dtype=np.uint8)
    with atomic_path(path, overwrite=overwrite) as tmp:
        with open(tmp, "wb") as fh:
            np.savez_compressed(fh, **payload)
    return path


def read_product(path, *, format: str, format_version: int, remedy: str,
                 limits=None, state_schema=None) -> tuple[dict, dict]:
    """Read and check a product file.

    Nothing is inflated before it is checked: the manifest (at most 64 MiB) is read first,
    then every array's ``.npy`` header (dtype, shape) is checked against the product's schema
    (:func:`check_product`: numeric dtypes, shapes consistent with each other and with the
    manifest, JSON types and list lengths, the size limits of
    :class:`hsiffc.files.limits.ReadLimits`), and only then are the arrays read.

    Parameters
    ----------
    path : path-like
    format, format_version : str, int
        The expected product type, and the newest schema version this hsiffc reads.
    remedy : str
        How to make a good file (ends the "not found" and "unreadable" messages).
    limits : ReadLimits, optional
        Size limits (default :func:`hsiffc.files.limits.default_limits`).
    state_schema : callable, optional
        Passed to :func:`check_product`.

    Returns
    -------
    manifest : dict
    arrays : dict of str to ndarray

    Raises
    ------
    DataFormatError
        Missing, unreadable or truncated file, no or invalid manifest, another product type or
        a newer schema, or content that breaks the schema; one line naming the file and the
        field.
    """
    from ..files.atomic import require_regular_input
    from ..files.limits import default_limits

    path = Path(path)
    if not path.exists():
        raise DataFormatError(f"{format} file not found; {remedy}", path=path)
    require_regular_input(path, what=f"{format} file")
    limits = limits or default_limits()
    try:
        with zipfile.ZipFile(path) as zf:
            headers = _npy_headers(zf, path, remedy)
            if MANIFEST not in headers:
                raise DataFormatError(f"no {MANIFEST} inside: not an hsiffc {format} file",
                                      path=path)
            manifest = _manifest(zf, headers.pop(MANIFEST), path, format, format_version)
            check_product(format, manifest, {k: h[:2] for k, h in headers.items()}, path=path,
                          limits=limits, remedy=remedy, state_schema=state_schema)
            arrays = {}
            for name, (_, _, member) in headers.items():
                with zf.open(member) as fh:
                    arrays[name] = np.lib.format.read_array(fh, allow_pickle=False)
    except HsiffcError:
        raise
    except (zipfile.BadZipFile, zipfile.LargeZipFile, ValueError, OSError, EOFError,
            NotImplementedError, zlib.error) as exc:
        raise DataFormatError(f"not a readable {format} file ({exc}); it may be truncated: "
                              f"{remedy}", path=path) from exc
    return manifest, arrays


_MANIFEST_MAX = 64 << 20
_NUMERIC = "biuf"  # bool, signed and unsigned integers, floats


def _npy_headers(zf, path, remedy: str) -> dict:
    """name -> (shape, dtype, member) of every ``.npy`` member, from its header alone; the
    size the header declares must be the member's size (the zip's own record)."""
    out = {}
    for info in zf.infolist():
        if not info.filename.endswith(".npy"):
            raise DataFormatError(f"member {info.filename!r} is not an array (.npy); not a file "
                                  "hsiffc wrote", path=path)
        name = info.filename[:-4]
        with zf.open(info) as fh:
            version = np.lib.format.read_magic(fh)
            read = (np.lib.format.read_array_header_1_0 if version == (1, 0)
                    else np.lib.format.read_array_header_2_0)
            shape, fortran, dtype = read(fh)
            start = fh.tell()
        if dtype.hasobject or dtype.kind not in _NUMERIC or dtype.fields is not None:
            raise DataFormatError(f"array {name!r} holds {dtype} values, not numbers; the file "
                                  f"was altered: {remedy}", path=path)
        nbytes = int(np.prod(shape, dtype=object)) * dtype.itemsize
        if start + nbytes != info.file_size:
            raise DataFormatError(f"array {name!r} declares {shape} {dtype} ({nbytes:,} bytes) "
                                  f"but its member holds {info.file_size - start:,}; the file is "
                                  f"damaged or altered: {remedy}", path=path)
        out[name] = (tuple(int(s) for s in shape), dtype, info)
    return out


def _manifest(zf, header, path, format: str, format_version: int) -> dict:
    from ..files.parsers import load_json

    shape, dtype, info = header
    if dtype != np.uint8 or len(shape) != 1 or shape[0] > _MANIFEST_MAX:
        raise DataFormatError(f"the {MANIFEST} member is {shape} {dtype}, not a JSON text of at "
                              f"most {_MANIFEST_MAX >> 20} MiB", path=path)
    with zf.open(info) as fh:
        text = np.lib.format.read_array(fh, allow_pickle=False).tobytes()
    manifest = load_json(text, path=path, what=MANIFEST)
    if not isinstance(manifest, dict) or manifest.get("format") != format:
        found = manifest.get("format") if isinstance(manifest, dict) else manifest
        raise DataFormatError(f"format is {found!r}, expected {format!r}", path=path)
    version = manifest.get("format_version", 0)
    if not isinstance(version, int) or version > format_version:
        raise DataFormatError(f"{format} format version {version!r} is newer than this hsiffc "
                              f"({__version__}) reads ({format_version}); upgrade hsiffc",
                              path=path)
    return manifest


# -- the schema of what a product file holds --------------------------------------------------
# A stage's fitted state is described by its own ``state_schema`` (a class attribute, or a
# function of the step's parameters where the state depends on them): field -> JSON kind
# ("bool", "int", "number", "numbers", "dict", "str", "any"; "|null" allows null) or array spec
# (dtype kinds, dims, or a list of dims the array may have). Dims are "H"/"W" (the frame,
# shared by the whole file), another capital letter (a size shared within the step, e.g.
# bands), or the name of a list field (its length).
_DTYPE_WORDS = {"f": "floats", "u": "unsigned integers (DQ bits)"}
_MAX_SIZE = 65536  # a step's own sizes (bands, coefficients, exposures): far above any real one
_KINDS = {"bool": (bool,), "int": (int,), "number": (int, float), "dict": (dict,), "str": (str,),
          "numbers": (list,), "any": (object,)}
_WORDS = {"bool": "true or false", "int": "a whole number", "number": "a number",
          "numbers": "a list of numbers", "dict": "a table", "str": "a text", "any": "a value"}


def _json_ok(value, kind: str) -> bool:
    kinds = kind.split("|")
    if value is None:
        return "null" in kinds or "any" in kinds
    base = kinds[0]
    if isinstance(value, bool) and base not in ("bool", "any"):
        return False
    if not isinstance(value, _KINDS[base]):
        return False
    if base == "numbers":
        return all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in value)
    return True


class _Dims:
    """Sizes named in array specs, bound on first use and checked on every later one."""

    def __init__(self, path, limits, remedy: str):
        self.path, self.limits, self.remedy, self.frame = path, limits, remedy, {}

    def fail(self, where: str, message: str):
        raise DataFormatError(f"{where} {message}; the file is damaged or was altered: "
                              f"{self.remedy}", path=self.path)

    def bind(self, where: str, name: str, size: int, scope: dict, lengths: dict) -> None:
        if name in ("H", "W"):
            table, what = self.frame, f"the frame's {'height' if name == 'H' else 'width'}"
        elif name in lengths:
            if size != lengths[name]:
                self.fail(where, f"has {size} entries along {name!r}, which lists "
                                 f"{lengths[name]}")
            return
        elif name.endswith("_"):
            self.fail(where, f"is sized by the field {name!r}, which the file does not hold")
        else:
            table, what = scope, f"size {name}"
        if name not in ("H", "W") and size > _MAX_SIZE:
            self.fail(where, f"has {size:,} entries along {name}, more than {_MAX_SIZE:,}")
        if table.setdefault(name, size) != size:
            self.fail(where, f"has {what} {size}, but other arrays of the file have "
                             f"{table[name]}")
        if name in ("H", "W") and len(self.frame) == 2:
            self.limits.check_frames(path=self.path, n_frames=1, itemsize=1,
                                     shape=(self.frame["H"], self.frame["W"]))


def _check_arrays(dims: _Dims, where: str, schema: dict, headers: dict, fields: dict) -> None:
    """Check the arrays ``headers`` (key -> (shape, dtype)) of one part against ``schema``."""
    lengths = {k: len(v) for k, v in fields.items() if isinstance(v, list)}
    lengths.update({k: h[0][0] for k, h in headers.items() if len(h[0]) == 1})
    scope: dict = {}
    for key, (shape, dtype) in headers.items():
        spec = schema.get(key)
        here = f"{where} array {key!r}"
        if spec == "numbers" and len(shape) == 1:  # a list stored as an array
            continue
        if not isinstance(spec, tuple):
            dims.fail(here, "is not one this part of the file stores")
        kinds, names = spec
        if isinstance(names, list):  # alternatives: the one with as many axes as the array
            names = next((n for n in names if len(n) == len(shape)), names[0])
        if dtype.kind not in kinds:
            dims.fail(here, f"holds {dtype} values, expected {_DTYPE_WORDS.get(kinds, 'numbers')}")
        if len(shape) != len(names):
            dims.fail(here, f"has shape {shape}, expected {len(names)} axes ({', '.join(names)})")
        for name, size in zip(names, shape):
            dims.bind(here, name, size, scope, lengths)


def _check_fields(dims: _Dims, where: str, schema: dict, fields: dict) -> None:
    for key, value in fields.items():
        kind = schema.get(key)
        if kind is None or isinstance(kind, tuple):
            dims.fail(f"{where} field {key!r}", "is not one this part of the file stores")
        if not _json_ok(value, kind):
            got = "null" if value is None else type(value).__name__
            dims.fail(f"{where} field {key!r}", f"is {got} ({str(value)[:40]}), expected "
                                               f"{_WORDS[kind.split('|')[0]]}")


def _check_calibration(dims: _Dims, where: str, manifest, headers: dict) -> None:
    if not isinstance(manifest, dict) or not isinstance(manifest.get("domain"), dict):
        dims.fail(where, "has no 'domain' table")
    shape = manifest["domain"].get("frame_shape")
    if not (isinstance(shape, list) and len(shape) == 2
            and all(isinstance(s, int) and not isinstance(s, bool) for s in shape)):
        dims.fail(f"{where} field 'domain.frame_shape'", f"is {shape!r}, expected [H, W]")
    for name, size in zip("HW", shape):
        dims.bind(f"{where} field 'domain.frame_shape'", name, size, {}, {})
    declared = manifest.get("arrays")
    for key, (shape_, dtype) in headers.items():
        if isinstance(declared, dict):
            want = declared.get(key)
            if not isinstance(want, dict):
                dims.fail(f"{where} array {key!r}", "is not listed in its manifest")
            if want.get("dtype") != dtype.name or list(want.get("shape", ())) != list(shape_):
                dims.fail(f"{where} array {key!r}", f"is {list(shape_)} {dtype.name}, its "
                                                    f"manifest says {want.get('shape')} "
                                                    f"{want.get('dtype')}")
    _check_arrays(dims, where, {k: (_NUMERIC, ("H", "W")) for k in headers}, headers, {})


def _check_pipeline(dims: _Dims, manifest: dict, headers: dict, state_schema) -> None:
    steps = manifest.get("steps")
    if not isinstance(steps, list) or not steps:
        dims.fail("the manifest's field 'steps'", "is not a non-empty list")
    claimed = set()
    for i, spec in enumerate(steps):
        where = f"step {i + 1}"
        if not (isinstance(spec, dict) and isinstance(spec.get("name"), str)
                and isinstance(spec.get("stage"), str) and isinstance(spec.get("params"), dict)
                and isinstance(spec.get("state"), (dict, type(None)))):
            dims.fail(where, "is not a table with a text 'name' and 'stage', a 'params' table "
                             "and a 'state' table or null")
        name = spec["name"]
        where = f"step {name!r}"
        if "/" in name:
            dims.fail(where, "has a '/' in its name")
        for key, ref in spec["params"].items():  # calibrations stored inside the file
            if isinstance(ref, dict) and ref.get("embedded") is not None:
                prefix = f"{name}/{key}/"
                part = {k[len(prefix):]: h for k, h in headers.items() if k.startswith(prefix)}
                claimed |= {prefix + k for k in part}
                _check_calibration(dims, f"{where} calibration {key!r}", ref["embedded"], part)
        prefix = f"{name}/"
        state = {k[len(prefix):]: h for k, h in headers.items()
                 if k.startswith(prefix) and "/" not in k[len(prefix):]}
        claimed |= {prefix + k for k in state}
        if spec["state"] is None:
            if state:
                dims.fail(f"{where} array {next(iter(state))!r}", "belongs to no fitted state")
            continue
        schema = None if state_schema is None else state_schema(spec["stage"], spec["params"])
        if schema is None:  # a plugin that declares nothing: numbers only (checked already)
            continue
        _check_fields(dims, f"{where} state", schema, spec["state"])
        _check_arrays(dims, f"{where} state", schema, state, spec["state"])
    stray = sorted(set(headers) - claimed)
    if stray:
        dims.fail(f"array {stray[0]!r}", "belongs to no step of the pipeline")


def check_product(format: str, manifest: dict, headers: dict, *, path, limits,
                  remedy: str = "write it again with hsiffc", state_schema=None) -> None:
    """The one schema check of what a product file holds, run on the manifest and the arrays'
    ``.npy`` headers before any array is read.

    Every array holds numbers (checked with the headers); its shape fits the others (one frame
    size for the whole file, within the size limits) and the manifest (a calibration's
    declared arrays, a state's list lengths: e.g. one stored dark per listed exposure); a
    fitted state's JSON fields have the types its stage writes (its ``state_schema``); no
    array is left over; all arrays together fit ``limits.max_bytes``.

    Parameters
    ----------
    format : str
        The product type ("hsiffc-calibration", "hsiffc-pipeline"; others: numbers and sizes
        only).
    manifest : dict
    headers : dict
        Array name -> (shape, dtype) from the ``.npy`` headers.
    path : path-like
        The file (for the messages).
    limits : ReadLimits
    remedy : str
        How to make a good file (ends the messages).
    state_schema : callable, optional
        ``state_schema(stage, params)``: the schema of the fitted state of a step of that
        registered stage with those parameters, or None to check numbers only (the pipeline
        passes its registry's lookup: each stage's own ``state_schema``). Without it, a
        pipeline's states are checked for numbers and sizes only.

    Raises
    ------
    DataFormatError
        One line naming the file, the step or part, the field and what is wrong.
    """
    total = sum(int(np.prod(shape, dtype=object)) * dtype.itemsize
                for shape, dtype in headers.values())
    limits.check_bytes(path=path, nbytes=total, what=f"the arrays of this {format} file")
    dims = _Dims(path, limits, remedy)
    if format == "hsiffc-calibration":
        _check_calibration(dims, "the calibration", manifest, headers)
    elif format == "hsiffc-pipeline":
        _check_pipeline(dims, manifest, headers, state_schema)
