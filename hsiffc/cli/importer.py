"""``hsiffc import``: any supported input, with its resolved metadata, as one hsiffc TIFF."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from .common import add_input_options, add_overwrite, input_overrides


def register(sub) -> None:
    """Add ``import`` to the parser's sub-parsers.

    Parameters
    ----------
    sub : argparse._SubParsersAction
        What ``ArgumentParser.add_subparsers()`` returned (see :func:`hsiffc.cli.build_parser`).
    """
    p = sub.add_parser(
        "import", help="write frames of any supported format as one self-describing hsiffc TIFF",
        description="Read TIFF/PNG/ENVI/FITS files, folders, globs or an EMVA 1288 measurement "
                    "with their metadata (file, then sidecar, then options) and write them as "
                    "one hsiffc TIFF (raw DN kept, one page per frame, metadata as JSON).")
    p.add_argument("inputs", nargs="+", type=Path, help="files, folders or globs")
    p.add_argument("-o", "--output", type=Path, required=True, help="hsiffc TIFF to write")
    p.add_argument("--compression", choices=("none", "zlib", "lzw", "zstd"), default="zlib",
                   help="lossless compression of the pages (default zlib)")
    add_input_options(p)
    add_overwrite(p)
    p.set_defaults(func=_cmd_import, input_args=("inputs",), output_args=("output",))


def _cmd_import(args) -> int:
    from ..errors import DataFormatError
    from ..io import open_source, write_sweep
    from ..io.tiff import WRITABLE_DTYPES

    with open_source(args.inputs, overrides=input_overrides(args)) as src:
        print(src.describe())
        if src.dtype.type not in WRITABLE_DTYPES:  # before reading every frame
            raise DataFormatError(
                f"frames of dtype {src.dtype} cannot be stored in an hsiffc TIFF ((u)int8/16/32 "
                "or float32/64) without changing their values, which import never does; "
                "convert the files to one of those types first", path=src.label)
        sweep = src.to_sweep()
    meta = dict(sweep.meta)
    meta["imported_from"] = [str(f) for f in src.files]
    compression = None if args.compression == "none" else args.compression
    write_sweep(args.output, replace(sweep, meta=meta), overwrite=args.overwrite,
                compression=compression)
    print(f"wrote {args.output}: {sweep.summary()}")
    return 0
