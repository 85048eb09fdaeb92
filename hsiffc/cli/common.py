"""What every command shares: the JSON writer and small formatting helpers."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ..errors import HsiffcError

DEFAULT_SAMPLES = Path("sample_cubes")


def declared(args, kind: str) -> list:
    """The values of the arguments a sub-parser declared as ``kind`` (``input_args``,
    ``output_args`` or ``output_dirs`` in its defaults), lists flattened, None dropped.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed arguments.
    kind : {"input_args", "output_args", "output_dirs"}
        Which declaration to read.

    Returns
    -------
    list
        Paths (or path strings) in declaration order.
    """
    out = []
    for name in getattr(args, kind, ()):
        value = getattr(args, name, None)
        if value is None:
            continue
        out += list(value) if isinstance(value, (list, tuple)) else [value]
    return out


def input_files(values) -> list:
    """Every existing file a command's input arguments stand for, so that the write policy
    protects them all, not only the names typed: the image files of a folder or a glob (and
    the data files beside an ENVI header: same name, another suffix), and the descriptor and
    images of an EMVA 1288 measurement. Arguments that name nothing are skipped (the command
    reports them); only folder listings and EMVA descriptors are read, never an image.

    Parameters
    ----------
    values : list of path-like
        The declared input arguments (:func:`declared` ``"input_args"``).

    Returns
    -------
    list of Path
    """
    from ..errors import DataFormatError
    from ..io.emva import emva_files, has_emva_descriptor
    from ..io import expand_inputs

    out: list[Path] = []
    for value in values:
        path = Path(value)
        if path.suffix.lower() == ".txt" or (path.is_dir() and has_emva_descriptor(path)):
            try:  # an EMVA 1288 measurement: its descriptor and the images it names
                out += emva_files(path)
            except (DataFormatError, OSError):
                pass  # the command reports what is wrong with it
            continue
        try:
            files = expand_inputs(value)
        except (DataFormatError, OSError):
            continue
        out += files
        stems: dict[Path, set] = {}
        for f in files:
            if f.suffix.lower() == ".hdr":  # an ENVI header: its data file shares the stem
                stems.setdefault(f.parent, set()).add(f.stem)
        for parent, names in stems.items():
            out += [q for q in parent.iterdir()
                    if (q.stem in names or q.name in names) and q.is_file()]
    return out


def check_declared_outputs(args) -> None:
    """Refuse, before any work, outputs that exist (without ``--overwrite``), are inputs, are
    symbolic links or folders, or name one file twice; and report folders that hold files.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed arguments with the ``output_args``/``output_dirs`` declarations.

    Raises
    ------
    OutputError
        One of the outputs cannot be written under the write policy (the message names it).
    """
    from ..files.atomic import check_output, check_output_folder

    seen = {}
    for path in declared(args, "output_args"):
        key = os.path.abspath(path)
        if key in seen:
            raise HsiffcError(f"{path}: given for two outputs ({seen[key]} and this one); give "
                              "each output its own file name")
        seen[key] = path
        check_output(path)
    for folder in declared(args, "output_dirs"):
        check_output_folder(folder)


def nonfinite_samples(sweep, path, *, what: str) -> int:
    """How many samples of ``sweep`` are NaN/inf; raises HsiffcError when no light frame holds a
    finite sample (there is nothing to ``what``).

    Parameters
    ----------
    sweep : Sweep
        Frames read from ``path``.
    path : str or Path
        Their file (for the message).
    what : str
        What the command would do (e.g. ``"calibrate"``), for the message.

    Returns
    -------
    int
        Number of non-finite samples (0 for integer data).

    Raises
    ------
    HsiffcError
        No light frame holds a finite sample.
    """
    data = np.asarray(sweep.data)
    if data.dtype.kind != "f":
        return 0
    finite = np.isfinite(data)
    light = np.asarray(sweep.kind) == "light"
    if not finite[light].any():
        raise HsiffcError(f"{path}: no finite pixel value in its {int(light.sum())} light frames "
                          f"(all NaN/inf); nothing to {what}: check how the file was written")
    return int(finite.size - np.count_nonzero(finite))


def first_nonfinite(sweep) -> str:
    """Where the first NaN/inf sample of a float sweep is, as text.

    Parameters
    ----------
    sweep : Sweep
        Float frames with at least one non-finite sample.

    Returns
    -------
    str
        ``"frame K, pixel (ROW, COL)"``.
    """
    k, r, c = (int(i) for i in np.argwhere(~np.isfinite(sweep.data))[0])
    return f"frame {k}, pixel ({r}, {c})"


def add_overwrite(parser, help: str = "replace an existing output file") -> None:
    """The ``--overwrite`` option every writing command has (it sets the write policy).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The sub-command's parser.
    help : str
        Help text of the option.
    """
    parser.add_argument("--overwrite", action="store_true", help=help)


def write_json(path: Path, doc) -> None:
    """Write ``doc`` as indented JSON to ``path`` atomically.

    Parameters
    ----------
    path : str or Path
        Output file (through the one writer: never over an existing file unless the command's
        write policy allows it).
    doc : dict or list
        JSON-able document (numpy values and paths converted; NaN and inf written as null).
    """
    from ..files.atomic import atomic_write_text
    from ..files.jsonsafe import json_safe

    # non-finite floats become null (JSON has no NaN); allow_nan=False proves none is left
    text = json.dumps(json_safe(doc), indent=2, default=json_default, allow_nan=False)
    atomic_write_text(Path(path), text + "\n")


def json_default(obj):
    """JSON encoder fallback for numpy scalars and arrays and paths.

    Parameters
    ----------
    obj : object
        What :mod:`json` could not encode.

    Returns
    -------
    object
        A Python scalar, list or str.

    Raises
    ------
    TypeError
        For any other type.
    """
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"not JSON-serialisable: {type(obj).__name__}")


def add_input_options(parser) -> None:
    """The metadata options every command that reads frames accepts (lowest priority: values the
    files or their sidecar give come first; see docs/formats-and-metadata.md).

    Parameters
    ----------
    parser : argparse.ArgumentParser
        The sub-command's parser; gets the group "input metadata".
    """
    g = parser.add_argument_group(
        "input metadata", "for files that do not carry it (the file, then a sidecar "
        "hsiffc.toml/hsiffc.csv next to it, then these options)")
    from .args import count, exposure_ms

    g.add_argument("--exposure-ms", type=exposure_ms, default=None, metavar="MS",
                   help="exposure time of every frame, in milliseconds")
    g.add_argument("--bit-depth", type=count, default=None, metavar="BITS",
                   help="ADC bit depth (full scale 2**BITS-1 DN); default: from the file, else "
                        "detected or assumed from the dtype with a warning")
    g.add_argument("--kind", choices=("light", "dark"), default=None,
                   help="frame kind (default light)")
    g.add_argument("--mosaic", default=None, metavar="SPEC",
                   help="4x4, 5x5, WxH (tile width x height) or an IMEC sensor XML (frames are "
                        "then cropped to its filter area and get its band wavelengths)")
    g.add_argument("--illumination", default=None, metavar="LABEL",
                   help="label of the light source")
    g.add_argument("--bit-shift", type=int, default=None, metavar="N",
                   help="right shift for samples left-aligned in 16-bit words (4 for 12-bit, 6 "
                        "for 10-bit; 0 turns the detection off)")
    g.add_argument("--sidecar", type=Path, default=None, metavar="FILE",
                   help="sidecar (.toml or .csv) to use instead of hsiffc.toml/.csv next to "
                        "the data")


def input_overrides(args, **fixed):
    """:class:`hsiffc.io.Overrides` from the options of :func:`add_input_options` (``fixed``
    replaces some, e.g. ``kind="dark"``).

    Parameters
    ----------
    args : argparse.Namespace
        Parsed arguments.
    **fixed
        Metadata fields set by the command itself.

    Returns
    -------
    Overrides
    """
    from ..io import Overrides

    values = {name: getattr(args, name, None) for name in
              ("exposure_ms", "bit_depth", "kind", "mosaic", "illumination", "bit_shift",
               "sidecar")}
    values.update(fixed)
    return Overrides(**values)
