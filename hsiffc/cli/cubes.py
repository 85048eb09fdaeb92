"""Commands on cubes: ``quicklook``."""

from __future__ import annotations

from pathlib import Path

from ..errors import HsiffcError
from .args import real
from .common import add_overwrite


def register(sub) -> None:
    """Add this module's sub-commands to the parser's sub-parsers."""
    p = sub.add_parser(
        "quicklook", help="one PNG of a cube: pseudo-colour, bands, DQ map, a spectrum",
        description="Draw a cube (an output of hsiffc correct, or an ENVI, OME-TIFF or netCDF "
                    "cube hsiffc wrote) as one PNG: a pseudo-colour image from three "
                    "wavelengths, a grid of bands, the DQ map and the spectrum of a pixel or "
                    "region, to see at a glance whether the cube is right. A corrected file of "
                    "mosaic frames is shown as one spectrum per tile.")
    p.add_argument("cube", type=Path, help="cube file (.corrected.tif, .hdr, .ome.tif, .nc)")
    p.add_argument("-o", "--output", type=Path, required=True, help="PNG to write")
    p.add_argument("--rgb", type=real, nargs=3, default=None, metavar=("R_NM", "G_NM", "B_NM"),
                   help="wavelengths (nm) shown red, green, blue (nearest bands; default: "
                        "640 550 460 nm, or the long, middle and short end of a NIR cube)")
    p.add_argument("--bands", type=int, nargs="+", default=None, metavar="K",
                   help="band numbers of the grid, counted from 1 by wavelength as in every "
                        "table and warning (hsiffc info lists them; default: up to 12, evenly "
                        "spread)")
    p.add_argument("--pixel", type=int, nargs=2, default=None, metavar=("ROW", "COL"),
                   help="pixel whose spectrum is drawn (default: the centre)")
    p.add_argument("--region", type=int, nargs=4, default=None,
                   metavar=("ROW0", "ROW1", "COL0", "COL1"),
                   help="region (rows ROW0..ROW1-1, columns COL0..COL1-1) whose spectrum is "
                        "drawn instead of a pixel")
    p.add_argument("--frame", type=int, default=0,
                   help="frame of a corrected file holding several (default 0)")
    add_overwrite(p)
    p.set_defaults(func=_cmd_quicklook, input_args=("cube",), output_args=("output",))


def _cmd_quicklook(args) -> int:
    from ..cubes import quicklook, read_cube

    if args.output.suffix.lower() != ".png":
        raise HsiffcError(f"-o {args.output}: quicklook writes a PNG; name it .png")
    if args.pixel is not None and args.region is not None:
        raise HsiffcError("give --pixel or --region, not both")
    cube = read_cube(args.cube, frame=args.frame)
    try:
        quicklook(cube, args.output, rgb_nm=args.rgb, bands=args.bands, pixel=args.pixel,
                  region=args.region, title=args.cube.name)
    except ValueError as exc:
        raise HsiffcError(str(exc)) from None
    print(f"wrote {args.output}")
    return 0
