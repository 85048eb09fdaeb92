"""One registry for built-in and third-party stages.

Built-ins are listed here; third parties declare entry points in the group ``hsiffc.stages``
of their own ``pyproject.toml``::

    [project.entry-points."hsiffc.stages"]
    hot_pixel_repair = "hsiffc_hotpixel:HotPixelRepair"

Entries are ``"module:Class"`` strings, imported only when a stage is used. A plugin that fails
to import gives a warning naming its package, not a crash. Pipelines loaded from files resolve
stages by these registered names only, never by an import path read from the file.
"""

from __future__ import annotations

import importlib
import warnings
from dataclasses import dataclass
from importlib.metadata import entry_points

from ..errors import HsiffcWarning, UnknownStageError
from ..data.params import did_you_mean, unknown_parameters

GROUP = "hsiffc.stages"

BUILTIN = {
    "dark": "hsiffc.stages.dark:DarkSubtract",
    "alpha_mask": "hsiffc.stages.alpha:AlphaMask",
    "two_point_ffc": "hsiffc.stages.ffc:TwoPointFFC",
    "polynomial_ffc": "hsiffc.stages.ffc:PolynomialFFC",
    "flat_field": "hsiffc.stages.ffc:FlatFieldFFC",
    "linearise": "hsiffc.stages.linearise:LeakageLinearise",
    "model_ffc": "hsiffc.stages.model_ffc:ModelFFC",
    "reconstruct": "hsiffc.stages.reconstruct:Reconstruct",
    "reflectance": "hsiffc.stages.reflectance:Reflectance",
    "filter": "hsiffc.stages.filter:FilterStage",
}


class PluginWarning(HsiffcWarning):
    """A third-party stage could not be loaded."""


@dataclass(frozen=True)
class StageEntry:
    name: str
    target: str  # "module:Class"
    source: str  # "hsiffc (built-in)" or "<distribution> <version>"


def entries() -> dict[str, StageEntry]:
    """Every registered stage, built-ins first; a plugin cannot shadow a built-in name."""
    out = {n: StageEntry(n, t, "hsiffc (built-in)") for n, t in BUILTIN.items()}
    for ep in entry_points(group=GROUP):
        dist = getattr(ep, "dist", None)
        source = f"{dist.name} {dist.version}" if dist is not None else "unknown package"
        if ep.name in out:
            warnings.warn(f"stage {ep.name!r} from {source} ignored: the name is taken by "
                          f"{out[ep.name].source}", PluginWarning, stacklevel=2)
            continue
        out[ep.name] = StageEntry(ep.name, ep.value, source)
    return out


def get(name: str):
    """The stage class registered as ``name``.

    Raises
    ------
    UnknownStageError
        No stage has that name (the message suggests the closest and lists every one), or
        its plugin failed to load. A ``ParameterError`` (``ValueError``) and a ``KeyError``.
    """
    table = entries()
    if name not in table:
        raise UnknownStageError(
            f"no stage named {name!r}; {did_you_mean(name, table)}installed stages: "
            f"{', '.join(sorted(table))} (third-party stages register under the entry-point "
            f"group {GROUP!r}; hsiffc stages lists them)")
    entry = table[name]
    module, _, attr = entry.target.partition(":")
    try:
        cls = getattr(importlib.import_module(module), attr)
    except (Exception, SystemExit) as exc:  # a broken plugin must not take hsiffc down, nor
        # end it: a plugin calling sys.exit(0) on import would end fit/correct with status 0
        what = (f"it called sys.exit({exc.code!r}) while being imported"
                if isinstance(exc, SystemExit) else str(exc))
        warnings.warn(f"stage {name!r} from {entry.source} could not be loaded "
                      f"({type(exc).__name__}: {what})", PluginWarning, stacklevel=2)
        raise UnknownStageError(f"stage {name!r} is installed ({entry.source}) but failed to "
                                f"load: {what}") from exc
    if not getattr(cls, "name", ""):
        cls.name = name
    return cls


def check_param_names(name: str, cls, params) -> None:
    """Refuse a parameter the stage class does not take, before it is built: one line naming
    the stage, the parameter, the closest valid name and every valid one.

    Raises
    ------
    ParameterError
    """
    unknown_parameters(f"stage {name!r}", params, cls._param_names())


def create(name: str, **params):
    """An instance of the stage registered as ``name``.

    Raises
    ------
    UnknownStageError
        No stage has that name (a ``ParameterError``).
    ParameterError
        A parameter the stage does not take (the message suggests the closest).

    Examples
    --------
    >>> create("dark")
    DarkSubtract(average='median', match='exposure', calibration=None)
    >>> create("alpha_mask", threshold_percnt=12)  # doctest: +ELLIPSIS
    Traceback (most recent call last):
    ...
    hsiffc.errors.ParameterError: stage 'alpha_mask' has no parameter 'threshold_percnt'; did you mean 'threshold_percent'? valid: calibration, threshold_percent...
    """
    cls = get(name)
    check_param_names(name, cls, params)
    return cls(**params)


def first_sentence(doc: str) -> str:
    """The first sentence of a docstring's first paragraph, on one line (a summary that
    runs over two source lines is not cut at the line's end).

    Examples
    --------
    >>> first_sentence("Turn a frame into a cube, and keep\\n    its flags. More.\\n\\nNotes")
    'Turn a frame into a cube, and keep its flags.'
    """
    import re

    paragraph = " ".join(doc.strip().split("\n\n")[0].split())
    paragraph = re.sub(r":\w+:`~?([^`]+)`", r"\1", paragraph).replace("``", "")  # roles
    m = re.match(r"(.+?[.!?])(\s|$)", paragraph)
    return m.group(1) if m else paragraph


def describe() -> list[dict]:
    """Name, class, source and load status of every registered stage (for ``hsiffc stages``)."""
    rows = []
    for entry in entries().values():
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore", PluginWarning)
                cls = get(entry.name)
            status = "ok"
            doc = first_sentence(cls.__doc__ or "")
        except KeyError as exc:
            status, doc = f"broken: {exc.__cause__}", ""
        rows.append({"name": entry.name, "target": entry.target, "source": entry.source,
                     "status": status, "summary": doc})
    return rows
