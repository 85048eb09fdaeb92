"""The ``filter`` stage: registered OpenCV and scikit-image calls run band by band, DQ-aware.

:data:`FILTERS` maps a filter's name to a :class:`FilterMethod`: the callable, its declared
parameters and their defaults, and whether it needs scikit-image (the optional extra
``pip install 'hsiffc[skimage]'``). Built in:

- ``gaussian`` (OpenCV ``GaussianBlur``; ``sigma`` in pixels of the band image),
- ``median`` (OpenCV ``medianBlur`` for ``size`` 3 and 5, SciPy ``median_filter`` above,
  both replicating the border),
- ``bilateral`` (OpenCV ``bilateralFilter``; ``sigma_color`` in DN, None: twice the band's
  noise, :func:`noise_dn`),
- ``total_variation`` (scikit-image ``denoise_tv_chambolle``; ``weight``),
- ``nl_means`` (scikit-image ``denoise_nl_means``; ``h`` as a fraction of the band's range,
  None: 0.8 x the band's noise, :func:`noise_dn`).

Plugins add filters with :func:`register_filter` (a package that registers filters when it is
imported declares that module under the entry-point group ``hsiffc.filters``, so a pipeline
loaded in a new process finds them). A pipeline file records a filter by its registered name
and parameters only, never by an import path read from the file.

Examples
--------
>>> import numpy as np
>>> from hsiffc.data.frame import Frame
>>> from hsiffc.data.mosaic import Mosaic
>>> rng = np.random.default_rng(0)
>>> f = Frame(rng.normal(100, 5, (40, 40)).astype(np.float32), np.zeros((40, 40), np.uint32),
...           {"exposure_ms": 5.0, "bit_depth": 12, "mosaic": Mosaic.square(2)})
>>> out = FilterStage(method="gaussian", params={"sigma": 1.5}).transform(f)
>>> bool(out.data.std() < f.data.std() / 2), out.data.dtype
(True, dtype('float32'))
>>> FilterStage(method="gausian").validate_params()
Traceback (most recent call last):
...
hsiffc.errors.ParameterError: filter: method='gausian' is not a registered filter; did you mean 'gaussian'? valid: bilateral, gaussian, median, nl_means, total_variation
"""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np

from ..errors import ParameterError
from ..data.params import Param, check_params, did_you_mean, unknown_parameters
from .base import Stage

__all__ = ["FILTERS", "FilterMethod", "FilterStage", "filter_image", "filter_planes",
           "describe_filters", "get_filter", "noise_dn", "register_filter"]

#: the entry-point group whose modules register filters when imported
GROUP = "hsiffc.filters"
#: what to install for the filters that need scikit-image
SKIMAGE_EXTRA = "pip install 'hsiffc[skimage]'"
#: spread (pixels) of the normalised-convolution fill of flagged samples
FILL_SIGMA = 2.0


@dataclass(frozen=True)
class FilterMethod:
    """A registered filter.

    Attributes
    ----------
    func : callable
        ``func(image, **params)``: a 2-D float32 image of one band (a cube band, or the
        sub-image of one mosaic position), no NaN, flagged samples already filled, returns an
        array of the same shape.
    params : dict of str to Param
        The parameters it takes, declared (checked with one-line errors).
    defaults : dict
        Their default values.
    summary : str
        What it does, in one line.
    needs : str or None
        A module it needs that hsiffc does not install by itself (``"skimage"``), checked
        when a stage using it is built.
    extra : str
        How to install what it needs (said in the error when ``needs`` is missing).
    scaled : bool
        The image is given scaled to [0, 1] over its samples' range and scaled back after
        the call (for parameters in units of the image's range: ``sigma_color``, ``weight``,
        ``h``); otherwise in DN as it is.
    source : str
        ``"hsiffc (built-in)"`` or who registered it.
    """

    func: Callable
    params: dict = field(default_factory=dict)
    defaults: dict = field(default_factory=dict)
    summary: str = ""
    needs: str | None = None
    extra: str = ""
    scaled: bool = False
    source: str = "hsiffc (built-in)"


def _gaussian(image, *, sigma):
    return cv2.GaussianBlur(image, (0, 0), sigmaX=float(sigma), sigmaY=float(sigma),
                            borderType=cv2.BORDER_REFLECT_101)


def _median(image, *, size):
    size = int(size)
    if size in (3, 5):  # OpenCV's float32 median takes these sizes only
        return cv2.medianBlur(image, size)
    from scipy.ndimage import median_filter

    return median_filter(image, size=size, mode="nearest")  # the same border as OpenCV's


def noise_dn(image) -> float:
    """The image's noise (DN), robustly: the MAD of horizontal neighbour differences
    over sqrt(2), times 1.4826 (0 for an image narrower than 2 pixels)."""
    d = np.diff(np.asarray(image, np.float32), axis=1)
    if d.size == 0:
        return 0.0
    return float(1.4826 * np.median(np.abs(d - np.median(d))) / np.sqrt(2.0))


def _bilateral(image, *, diameter, sigma_color, sigma_space):
    if sigma_color is None:
        sigma_color = 2.0 * noise_dn(image)
    if not sigma_color > 0:  # a noiseless band: nothing to remove
        return image
    return cv2.bilateralFilter(image, int(diameter), float(sigma_color), float(sigma_space),
                               borderType=cv2.BORDER_REFLECT_101)


def _total_variation(image, *, weight, max_num_iter):
    from skimage.restoration import denoise_tv_chambolle

    return denoise_tv_chambolle(image, weight=float(weight), max_num_iter=int(max_num_iter))


def _nl_means(image, *, h, patch_size, patch_distance):
    from skimage.restoration import denoise_nl_means

    sigma = noise_dn(image)  # skimage's estimate_sigma needs PyWavelets besides
    h = 0.8 * sigma if h is None else float(h)
    if h <= 0:  # a noiseless band: nothing to remove
        return image
    return denoise_nl_means(image, h=h, sigma=sigma, patch_size=int(patch_size),
                            patch_distance=int(patch_distance), fast_mode=True)


_POSITIVE = Param("number", low=0, low_open=True)
_ODD_WINDOW = Param("integer", low=3)

#: Registered filters: name -> :class:`FilterMethod` (:func:`register_filter` adds to it).
FILTERS: dict[str, FilterMethod] = {
    "gaussian": FilterMethod(_gaussian, {"sigma": Param("number", low=0, low_open=True,
                                                        unit="pixels")},
                             {"sigma": 1.0}, "Gaussian blur (OpenCV GaussianBlur)"),
    "median": FilterMethod(_median, {"size": _ODD_WINDOW}, {"size": 3},
                           "median of a size x size window (OpenCV medianBlur; SciPy above 5)"),
    "bilateral": FilterMethod(
        _bilateral, {"diameter": Param("integer", low=1),
                     "sigma_color": Param("number", low=0, low_open=True, unit="DN",
                                          optional=True),
                     "sigma_space": Param("number", low=0, low_open=True, unit="pixels")},
        {"diameter": 5, "sigma_color": None, "sigma_space": 2.0},
        "edge-preserving bilateral filter (OpenCV bilateralFilter); sigma_color in DN, None: "
        "twice the band's noise"),
    "total_variation": FilterMethod(
        _total_variation, {"weight": _POSITIVE, "max_num_iter": Param("integer", low=1)},
        {"weight": 0.1, "max_num_iter": 200},
        "total-variation denoising (scikit-image denoise_tv_chambolle); weight on the band "
        "scaled to [0, 1]", needs="skimage", extra=SKIMAGE_EXTRA, scaled=True),
    "nl_means": FilterMethod(
        _nl_means, {"h": Param("number", low=0, low_open=True, optional=True),
                    "patch_size": Param("integer", low=1),
                    "patch_distance": Param("integer", low=1)},
        {"h": None, "patch_size": 5, "patch_distance": 6},
        "non-local means (scikit-image denoise_nl_means); h as a fraction of the band's range, "
        "None: 0.8 x the band's noise (noise_dn)", needs="skimage", extra=SKIMAGE_EXTRA,
        scaled=True),
}
_BUILTIN_NAMES = frozenset(FILTERS)
_loaded_plugins = False


def register_filter(name: str, func: Callable, *, params: dict | None = None,
                    defaults: dict | None = None, summary: str = "", needs: str | None = None,
                    extra: str = "", scaled: bool = False, source: str = "plugin") -> FilterMethod:
    """Register a filter for the ``filter`` stage under ``name``; returns its record.

    Parameters
    ----------
    name : str
        The name pipelines use (``method = "name"``). A built-in name cannot be taken.
    func : callable
        ``func(image, **params)`` on one band's 2-D float32 image (DN, or [0, 1] with
        ``scaled``), returning an array of the same shape.
    params : dict of str to Param
        The parameters it takes (:class:`hsiffc.data.params.Param`); any other is refused.
    defaults : dict
        Default values of ``params`` (each declared parameter needs one).
    summary, needs, extra, scaled, source
        As :class:`FilterMethod`.

    Raises
    ------
    ParameterError
        A built-in name, a name that is not an identifier, or a parameter without a default.

    Examples
    --------
    >>> import numpy as np
    >>> rec = register_filter("doc_box", lambda im, *, k: np.asarray(im) * 0 + im.mean(),
    ...                       params={"k": Param("integer", low=1)}, defaults={"k": 3})
    >>> FilterStage(method="doc_box").get_params()
    {'method': 'doc_box', 'params': None}
    >>> del FILTERS["doc_box"]
    """
    if not isinstance(name, str) or not name.isidentifier():
        raise ParameterError(f"register_filter: name={name!r} is not valid; expected a name "
                             "of letters, digits and underscores")
    if name in _BUILTIN_NAMES:
        raise ParameterError(f"register_filter: {name!r} is a built-in filter; choose another "
                             "name")
    if not callable(func):
        raise ParameterError(f"register_filter: func={func!r} is not callable")
    params, defaults = dict(params or {}), dict(defaults or {})
    missing = sorted(set(params) - set(defaults))
    if missing:
        raise ParameterError(f"register_filter: parameter {missing[0]!r} of {name!r} has no "
                             "default; give defaults={...} for every declared parameter")
    unknown_parameters(f"filter {name!r} defaults", defaults, params)
    record = FilterMethod(func, params, defaults, summary, needs, extra, scaled, source)
    FILTERS[name] = record
    return record


def _load_plugins() -> None:
    """Import, once, the modules declared under the entry-point group ``hsiffc.filters``
    (they register their filters when imported); one that fails gives a PluginWarning."""
    global _loaded_plugins
    if _loaded_plugins:
        return
    _loaded_plugins = True
    from importlib.metadata import entry_points

    from .registry import PluginWarning

    for ep in entry_points(group=GROUP):
        try:
            ep.load()
        except (Exception, SystemExit) as exc:  # a broken plugin must not take hsiffc down
            warnings.warn(f"filters from {ep.value!r} could not be loaded "
                          f"({type(exc).__name__}: {exc})", PluginWarning, stacklevel=3)


def get_filter(name) -> FilterMethod:
    """The :class:`FilterMethod` registered as ``name``.

    Raises
    ------
    ParameterError
        No filter has that name (one line: the closest name and every valid one), or it needs
        a module that is not installed (naming the extra to install).
    """
    if name not in FILTERS:
        _load_plugins()
    if not isinstance(name, str) or name not in FILTERS:
        raise ParameterError(f"filter: method={name!r} is not a registered filter; "
                             f"{did_you_mean(name, FILTERS)}valid: {', '.join(sorted(FILTERS))}")
    record = FILTERS[name]
    if record.needs:
        try:
            importlib.import_module(record.needs)
        except ImportError:
            raise ParameterError(f"filter: method={name!r} needs {record.needs}, which is not "
                                 f"installed: {record.extra or 'install it'}") from None
    return record


def describe_filters() -> list[dict]:
    """Name, source, summary and status (``"ok"``, or what to install) of every registered
    filter, those of installed plugins included (for ``hsiffc stages``)."""
    _load_plugins()
    rows = []
    for name in sorted(FILTERS):
        try:
            get_filter(name)
            status = "ok"
        except ParameterError:
            status = f"needs {FILTERS[name].needs}: {FILTERS[name].extra or 'install it'}"
        rec = FILTERS[name]
        rows.append({"name": name, "source": rec.source, "summary": rec.summary,
                     "params": dict(rec.defaults), "status": status})
    return rows


def _fill_flagged(image, bad):
    """``image`` with its ``bad`` samples replaced by the normalised convolution of the good
    ones (Gaussian, :data:`FILL_SIGMA` pixels), or by their median where none is near."""
    good = (~bad).astype(np.float32)
    num = cv2.GaussianBlur(np.where(bad, np.float32(0), image), (0, 0), FILL_SIGMA,
                           borderType=cv2.BORDER_REFLECT_101)
    den = cv2.GaussianBlur(good, (0, 0), FILL_SIGMA, borderType=cv2.BORDER_REFLECT_101)
    fallback = np.float32(np.median(image[~bad]))
    with np.errstate(divide="ignore", invalid="ignore"):
        local = np.where(den > 1e-3, num / den, fallback)
    return np.where(bad, local, image).astype(np.float32)


def filter_image(image, dq, record: FilterMethod, params: dict) -> np.ndarray:
    """One band's 2-D image filtered by ``record`` with ``params`` (float32 DN).

    Samples with a DQ bit set (or not finite) are filled from their good neighbours before
    the call (normalised convolution, else the band's median), so a flagged outlier never
    spreads; they keep their input value in the output. With ``record.scaled`` the image is
    scaled to [0, 1] over its range for the call and back after it; nothing is clipped.
    An image without a good sample is returned unchanged.
    """
    image = np.ascontiguousarray(image, dtype=np.float32)
    bad = (np.asarray(dq) != 0) | ~np.isfinite(image)
    if bad.all() or image.size == 0:
        return image.copy()
    work = _fill_flagged(image, bad) if bad.any() else image.copy()  # a filter may write
    lo = hi = None
    if record.scaled:
        lo, hi = float(work.min()), float(work.max())
        if not hi > lo:  # a constant band: every filter keeps it
            return image.copy()
        work = ((work - lo) / (hi - lo)).astype(np.float32)
    out = np.asarray(record.func(work, **params), dtype=np.float64 if record.scaled
                     else np.float32)
    if out.shape != image.shape:
        raise ValueError(f"a filter returned shape {out.shape} for an image of {image.shape}")
    if record.scaled:
        out = out * (hi - lo) + lo
    return np.where(bad, image, out).astype(np.float32)


def filter_planes(data, dq, mosaic, record: FilterMethod, params: dict) -> np.ndarray:
    """``data`` filtered plane by plane: each band of a cube ``(H, W, B)``; each mosaic
    position's sub-image of a 2-D mosaic frame (the samples a whole tile apart, so other
    bands' pixels are never mixed in); a 2-D frame without a mosaic as one image."""
    out = np.array(data, dtype=np.float32, copy=True)
    if out.ndim == 3:
        for b in range(out.shape[2]):
            out[:, :, b] = filter_image(data[:, :, b], dq[:, :, b], record, params)
        return out
    if mosaic is None:
        return filter_image(data, dq, record, params)
    ph, pw = mosaic.tile_shape
    oy, ox = mosaic.offset
    for r in range(ph):
        for c in range(pw):
            sl = (slice((r + oy) % ph, None, ph), slice((c + ox) % pw, None, pw))
            if out[sl].size:
                out[sl] = filter_image(data[sl], dq[sl], record, params)
    return out


class FilterStage(Stage):
    """Run a registered filter (:data:`FILTERS`: OpenCV and scikit-image calls) band by band.

    On a cube every band image is filtered; on a mosaic frame every mosaic position's
    sub-image (the samples a whole tile apart), so neighbouring pixels of other bands are never
    mixed. DQ-aware: flagged samples are filled from their good neighbours before the call and
    keep their value and flags; the flags are carried through unchanged. Values stay float32
    DN: filters whose parameters are in units of the image's range (``total_variation``,
    ``nl_means``) get each band scaled to [0, 1] and the result scaled
    back; nothing is clipped. The alpha plane is kept as it is. The data are no longer the
    sensor's response afterwards (stages that invert the raw response go before it).

    Stateless: ``fit`` only checks the parameters. A pipeline file records the filter by its
    registered name and ``params``.

    Parameters
    ----------
    method : str
        A registered filter: ``"gaussian"``, ``"median"``, ``"bilateral"``,
        ``"total_variation"`` or ``"nl_means"`` (the last two need
        ``pip install 'hsiffc[skimage]'``), or one a plugin registered
        (:func:`register_filter`).
    params : dict, optional
        The filter's parameters (e.g. ``{"sigma": 1.5}``; in TOML ``params = {sigma = 1.5}``);
        those not given take the filter's defaults.
    """

    name = "filter"
    #: fitted state as a pipeline file stores it (:func:`hsiffc.data.products.check_product`)
    state_schema = {"fitted_": "bool"}
    stateless = True
    removes = frozenset({"response"})
    param_spec = {"method": Param("string")}

    def __init__(self, *, method: str = "gaussian", params: dict | None = None):
        self.method = method
        self.params = params

    def validate_params(self) -> None:
        """Check ``method`` against :data:`FILTERS` and ``params`` against the filter's
        declared parameters (one-line :class:`~hsiffc.errors.ParameterError`)."""
        super().validate_params()
        self.resolved()

    def resolved(self) -> tuple[FilterMethod, dict]:
        """The filter's record and its full parameters (defaults, then ``params``)."""
        record = get_filter(self.method)
        given = self.params
        if given is None:
            given = {}
        if not isinstance(given, dict):
            raise ParameterError(f"filter: params={given!r} is not valid; expected a table of "
                                 f"the filter's parameters (e.g. params = {{sigma = 1.5}})")
        unknown_parameters(f"filter {self.method!r}", given, record.params)
        check_params(f"filter {self.method!r}", record.params, given)
        return record, {**record.defaults, **given}

    def transform(self, frame):
        """The frame filtered band by band (float32 DN; DQ and alpha unchanged)."""
        record, params = self.resolved()
        data = filter_planes(frame.data, frame.dq, frame.mosaic, record, params)
        return frame.replace(data=data, corrected_by=self.name)
