"""Radiometric enhancement of (thermal) frames for the feature detector.

Low-contrast thermal frames (16-bit counts that span a few hundred values of their range) give few tie
points unless they are stretched. Conte et al. 2018 (Table 4) compared, on one thermal block:

* no enhancement (the raw frames, here: a per-frame min-max stretch to 8 bit, since OpenCV's SIFT
  only accepts 8-bit input);
* "linear 2 %": one linear stretch for the *whole dataset*, cutting the tails of the flight's overall
  histogram; here ``percent`` is cut at *each* tail, so the 2nd and 98th percentiles of the flight map
  to 0 and 255;
* Wallis filtering after the linear 2 % stretch, with 16-bit or 8-bit intermediate precision.

Every function here is pure: it returns a new array and never modifies its input, so the original
radiometry stays available for the orthomosaic.

Units: raw frames are sensor counts (any integer or float dtype). :func:`linear_stretch`, :func:`wallis`
and :func:`minmax_stretch` return ``float32`` in [0, 1]; :func:`to_uint8` maps [0, 1] to 0..255.
The Wallis parameters (target mean and standard deviation) are in those [0, 1] units: multiply by
255 to compare with values quoted for 8-bit images.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

Method = Literal["auto", "none", "linear", "wallis"]

#: Number of bins of the exact histogram used for integer frames of up to 16 bits.
HIST_BINS_16 = 65536


@dataclass(frozen=True)
class EnhanceConfig:
    """How frames are turned into the 8-bit images the detector sees.

    Attributes
    ----------
    method:
        ``"none"``: per-frame min-max stretch to 8 bit (what a detector gets from unprocessed data);
        ``"linear"``: the dataset-wide linear stretch of :func:`stretch_params`;
        ``"wallis"``: the linear stretch followed by a Wallis filter (Conte 2018's best on thermal);
        ``"auto"`` (default): ``"wallis"`` for frames of more than 8 bits (radiometric thermal counts),
        ``"linear"`` for 8-bit frames (a visible or NIR camera's JPEGs), see :func:`resolve_method`.
    percent:
        Percentage of pixels cut at *each* tail of the flight's histogram by the linear stretch
        (default 2.0, the "linear 2 %" of Conte 2018).
    sample_frames:
        At most this many frames, evenly spaced over the flight, enter the flight's histogram
        (default 64): percentiles of a few dozen frames are stable to a count or two and the cost
        does not grow with the flight.
    quantise_first:
        ``False`` (default): the Wallis filter works on the stretched frame at full precision (the
        16-bit pipeline); ``True``: the stretched frame is quantised to 8 bit before the filter (the
        8-bit pipeline Conte 2018 found worse).
    wallis_mean, wallis_std:
        Target local mean and standard deviation, in [0, 1] units (defaults 0.5 and 0.2, i.e. 127.5
        and 51 in 8-bit counts).
    wallis_c:
        Contrast constant c in [0, 1] (default 0.95): c = 1 forces the target standard deviation
        everywhere; below 1 the gain ``c s_f / (c s_g + (1 - c) s_f)`` is capped at c / (1 - c) (19 for
        0.95) where the frame is flat, so noise there is not amplified without bound. On H20T forest
        frames c = 0.8, a common choice for visible images, gave about half the verified matches of
        c = 0.95 (``benchmarks/history/engine_measurements.md``); after a flight-wide stretch the local
        standard deviation of a thermal frame is ~1 % of the range, so the gain has to reach ~20.
    wallis_b:
        Brightness constant b in [0, 1] (default 0.9): 1 forces the target mean, 0 keeps the local mean.
    wallis_window:
        Side of the square window of the local mean and standard deviation, pixels (default 31, odd).
    """

    method: Method = "auto"
    percent: float = 2.0
    sample_frames: int = 64
    quantise_first: bool = False
    wallis_mean: float = 0.5
    wallis_std: float = 0.2
    wallis_c: float = 0.95
    wallis_b: float = 0.9
    wallis_window: int = 31

    def __post_init__(self) -> None:
        if self.method not in ("auto", "none", "linear", "wallis"):
            raise ValueError(
                f"EnhanceConfig.method {self.method!r} unknown; valid: auto, none, linear, wallis"
            )
        if not 0.0 <= self.percent < 50.0:
            raise ValueError(f"EnhanceConfig.percent must be in [0, 50), got {self.percent}")
        if self.sample_frames < 1:
            raise ValueError(f"EnhanceConfig.sample_frames must be >= 1, got {self.sample_frames}")
        _check_wallis(self.wallis_mean, self.wallis_std, self.wallis_c, self.wallis_b, self.wallis_window)


@dataclass(frozen=True)
class StretchParams:
    """A dataset-wide linear stretch: ``lo`` maps to 0, ``hi`` to 1 (sensor counts).

    ``percent`` is the share of pixels cut at each tail; ``n_frames`` and ``n_pixels`` say how many
    frames and pixels the histogram held.
    """

    lo: float
    hi: float
    percent: float
    n_frames: int
    n_pixels: int

    def to_dict(self) -> dict:
        return {"lo": self.lo, "hi": self.hi, "percent": self.percent, "n_frames": self.n_frames,
                "n_pixels": self.n_pixels}


# ----------------------------------------------------------------------------- histograms and stretch
def histogram16(img: np.ndarray) -> np.ndarray:
    """Exact histogram of an integer frame with values in 0..65535: ``int64`` counts, 65536 bins.

    Per-frame histograms can be computed in parallel (one per worker) and summed; their sum is what
    :func:`stretch_params` needs.

    Raises:
        TypeError: ``img`` is not an integer array.
        ValueError: a value of ``img`` lies outside 0..65535.
    """
    a = np.asarray(img)
    if a.dtype.kind not in "ui":
        raise TypeError(f"histogram16 needs an integer frame, got dtype {a.dtype}")
    if a.size and (a.min() < 0 or a.max() >= HIST_BINS_16):
        raise ValueError(f"histogram16: values must lie in 0..65535, got {a.min()}..{a.max()}")
    return np.bincount(a.ravel().astype(np.intp, copy=False), minlength=HIST_BINS_16)


def _sample_indices(n: int, k: int) -> np.ndarray:
    """``min(n, k)`` indices evenly spaced over 0..n-1 (first and last included), deterministic."""
    if n <= k:
        return np.arange(n)
    return np.unique(np.round(np.linspace(0, n - 1, k)).astype(int))


def stretch_params(
    images_or_histograms: Sequence,
    percent: float = 2.0,
    sample_frames: int | None = 64,
    loader: Callable[[object], np.ndarray] | None = None,
) -> StretchParams:
    """The dataset-wide linear stretch that cuts ``percent`` % of the pixels at each tail.

    Parameters
    ----------
    images_or_histograms:
        A sequence of frames (2-D arrays), of per-frame histograms (1-D ``int`` arrays of 65536 bins
        from :func:`histogram16`), a single summed histogram, or of anything ``loader`` turns into a
        frame (e.g. paths).
    percent:
        Share of pixels cut at each tail, percent (default 2.0).
    sample_frames:
        Use at most this many items, evenly spaced over the sequence (``None``: all of them).
    loader:
        Optional callable applied to each sampled item (only the sampled ones are loaded).

    Integer frames go through an exact 16-bit histogram: ``lo`` is the smallest count with at least
    ``percent`` % of the pixels at or below it, ``hi`` the largest with at least ``percent`` % at or
    above it. Float frames use ``numpy.percentile`` of the pixels (linear interpolation).

    Raises:
        ValueError: ``percent`` is outside [0, 50); no frames given; a histogram without 65536 bins; an integer frame
            with values outside 0..65535; float frames without a finite pixel, or an empty histogram.
        TypeError: a frame of a dtype neither integer nor float, or integer and float frames mixed.
    """
    if not 0.0 <= percent < 50.0:
        raise ValueError(f"stretch_params: percent must be in [0, 50), got {percent}")
    if isinstance(images_or_histograms, np.ndarray):
        # one summed histogram (1-D), one frame (2-D) or a stack of frames (3-D)
        arr = images_or_histograms
        items = list(arr) if arr.ndim == 3 else [arr]
    else:
        items = list(images_or_histograms)
    if not items:
        raise ValueError("stretch_params: no frames given")
    idx = _sample_indices(len(items), sample_frames or len(items))
    hist = np.zeros(HIST_BINS_16, dtype=np.int64)
    floats: list[np.ndarray] = []
    n_frames = 0
    for i in idx:
        item = loader(items[i]) if loader is not None else items[i]
        a = np.asarray(item)
        if a.ndim == 1:  # a histogram
            if a.size != HIST_BINS_16:
                raise ValueError(f"stretch_params: histogram {i} has {a.size} bins; expected {HIST_BINS_16}")
            hist += a.astype(np.int64)
        elif a.dtype.kind in "ui":
            hist += histogram16(a)
        elif a.dtype.kind == "f":
            floats.append(a[np.isfinite(a)].ravel())
        else:
            raise TypeError(f"stretch_params: frame {i} has unsupported dtype {a.dtype}")
        n_frames += 1
    if floats and hist.any():
        raise TypeError("stretch_params: mix of integer and float frames; convert them to one kind first")
    if floats:
        values = np.concatenate(floats)
        if values.size == 0:
            raise ValueError("stretch_params: frames hold no finite pixel")
        lo, hi = np.percentile(values, [percent, 100.0 - percent])
        return StretchParams(float(lo), float(hi), percent, n_frames, int(values.size))
    total = int(hist.sum())
    if total == 0:
        raise ValueError("stretch_params: the histogram is empty")
    cdf = np.cumsum(hist)
    cut = percent / 100.0 * total
    lo = int(np.searchsorted(cdf, max(cut, 1.0), side="left"))  # first value with cdf >= cut
    above = total - np.concatenate([[0], cdf[:-1]])  # pixels at or above each value
    hi = int(np.nonzero(above >= max(cut, 1.0))[0][-1])
    return StretchParams(float(lo), float(hi), percent, n_frames, total)


def linear_stretch(img: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """``(img - lo) / (hi - lo)`` clipped to [0, 1], as ``float32`` (16-bit counts stay exact).

    Raises:
        ValueError: ``hi`` is not greater than ``lo``.
    """
    if not hi > lo:
        raise ValueError(f"linear_stretch: need hi > lo, got lo={lo}, hi={hi}")
    a = np.asarray(img, dtype=np.float32)
    out = (a - np.float32(lo)) * np.float32(1.0 / (hi - lo))
    return np.clip(out, 0.0, 1.0, out=out)


def minmax_stretch(img: np.ndarray) -> np.ndarray:
    """Per-frame min-max stretch to [0, 1] (``float32``); a constant frame maps to 0."""
    a = np.asarray(img, dtype=np.float32)
    lo, hi = float(a.min()), float(a.max())
    if hi <= lo:
        return np.zeros_like(a)
    return linear_stretch(a, lo, hi)


def to_uint8(img: np.ndarray) -> np.ndarray:
    """A float image in [0, 1] -> ``uint8`` 0..255 (rounded, clipped); ``uint8`` input is copied.

    Integer frames of more than 8 bits are refused: stretch them first (:func:`linear_stretch`).

    Raises:
        TypeError: ``img`` is neither ``uint8`` nor float; stretch integer frames first (:func:`linear_stretch`).
    """
    a = np.asarray(img)
    if a.dtype == np.uint8:
        return a.copy()
    if a.dtype.kind != "f":
        raise TypeError(f"to_uint8 needs a float image in [0, 1] (got {a.dtype}); stretch it first")
    out = np.rint(np.clip(a, 0.0, 1.0) * 255.0)
    return out.astype(np.uint8)


# ----------------------------------------------------------------------------- Wallis filter
def _check_wallis(mean: float, std: float, c: float, b: float, window: int) -> None:
    if not 0.0 <= mean <= 1.0:
        raise ValueError(f"Wallis target mean must be in [0, 1], got {mean}")
    if not std > 0.0:
        raise ValueError(f"Wallis target std must be > 0, got {std}")
    if not 0.0 <= c <= 1.0:
        raise ValueError(f"Wallis contrast constant c must be in [0, 1], got {c}")
    if not 0.0 <= b <= 1.0:
        raise ValueError(f"Wallis brightness constant b must be in [0, 1], got {b}")
    if window < 3 or window % 2 == 0:
        raise ValueError(f"Wallis window must be an odd number of pixels >= 3, got {window}")


def local_mean_std(img: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation over a ``window`` x ``window`` box around every pixel (float64).

    Box filters (``cv2.boxFilter``, reflected borders) of the image and of its square; float64 keeps
    ``E[g^2] - E[g]^2`` accurate for low-contrast frames.
    """
    g = np.asarray(img, dtype=np.float64)
    k = (int(window), int(window))
    m = cv2.boxFilter(g, cv2.CV_64F, k, normalize=True, borderType=cv2.BORDER_REFLECT)
    m2 = cv2.boxFilter(g * g, cv2.CV_64F, k, normalize=True, borderType=cv2.BORDER_REFLECT)
    return m, np.sqrt(np.maximum(m2 - m * m, 0.0))


def wallis(
    img: np.ndarray,
    target_mean: float = 0.5,
    target_std: float = 0.2,
    c: float = 0.95,
    b: float = 0.9,
    window: int = 31,
) -> np.ndarray:
    """Wallis filter (Wallis 1976, in the form of Baltsavias 1991) -> ``float32`` in [0, 1].

    ``out = (g - m_g) r1 + b m_f + (1 - b) m_g`` with ``r1 = c s_f / (c s_g + (1 - c) s_f)``, where
    ``m_g``, ``s_g`` are the local mean and standard deviation of ``img`` over a ``window`` x ``window``
    box (:func:`local_mean_std`), ``m_f = target_mean`` and ``s_f = target_std``.

    Parameters
    ----------
    img:
        The frame, float in [0, 1] (e.g. the output of :func:`linear_stretch`); any real dtype is read
        as float.
    target_mean, target_std:
        Target local mean and standard deviation, [0, 1] units.
    c:
        Contrast constant in [0, 1]: with c = 1 the local standard deviation becomes ``target_std``;
        smaller values cap the gain at ``c / (1 - c)`` (19 for c = 0.95) in flat areas.
    b:
        Brightness constant in [0, 1]: with b = 1 the local mean becomes ``target_mean``.
    window:
        Odd side of the box, pixels.

    With c = b = 1 the output has the target mean and standard deviation in every window where the
    local statistics vary slowly. The result is clipped to [0, 1].
    """
    _check_wallis(target_mean, target_std, c, b, window)
    g = np.asarray(img, dtype=np.float64)
    m_g, s_g = local_mean_std(g, window)
    denom = c * s_g + (1.0 - c) * target_std
    with np.errstate(divide="ignore", invalid="ignore"):
        r1 = np.where(denom > 0.0, c * target_std / denom, 0.0)
    out = (g - m_g) * r1 + b * target_mean + (1.0 - b) * m_g
    return np.clip(out, 0.0, 1.0).astype(np.float32)


# ----------------------------------------------------------------------------- the detector's input
def grey(img: np.ndarray) -> np.ndarray:
    """A colour frame (H, W, 3 or 4; channels in R, G, B(, A) order, as :func:`aerocal.ingest.read_raw`
    returns them) as its luminance (ITU-R BT.601 weights, OpenCV's ``COLOR_RGB2GRAY``) in the frame's own
    dtype; a single-channel frame is returned as it is."""
    a = np.asarray(img)
    if a.ndim == 3 and a.shape[2] in (3, 4) and a.dtype in (np.uint8, np.uint16, np.float32):
        return cv2.cvtColor(a, cv2.COLOR_RGB2GRAY if a.shape[2] == 3 else cv2.COLOR_RGBA2GRAY)
    if a.ndim == 3 and a.shape[2] == 1:
        return a[:, :, 0]
    return a


def resolve_method(img: np.ndarray, method: Method) -> Method:
    """The enhancement ``method="auto"`` stands for on this frame: ``"wallis"`` for more than 8 bits,
    ``"linear"`` for 8-bit frames; any other method is returned unchanged.

    On 16-bit H20T thermal frames the Wallis filter gives many times the tie points of the linear stretch
    alone (``studies/enhancement_h20t.py``); on seneca's 8-bit JPEGs (NIR colour, their luminance) the linear
    stretch gives more verified matches than the Wallis filter (``benchmarks/history/engine_measurements.md``):
    its gain of up to 19 (``wallis_c`` 0.95), which a thermal frame's 1 % local contrast needs, lifts the
    JPEG's 8x8 block noise of flat crop fields into keypoints.
    """
    if method != "auto":
        return method
    return "linear" if np.asarray(img).dtype == np.uint8 else "wallis"


def enhance(
    img16: np.ndarray, params: StretchParams | None, config: EnhanceConfig | None = None
) -> np.ndarray:
    """The 8-bit grey image the feature detector sees, from a raw frame; ``img16`` is not modified.

    A colour frame is turned into its luminance first (:func:`grey`). ``params`` is the flight's
    :class:`StretchParams` (from :func:`stretch_params` over the frames' luminance); it may be ``None``
    only with ``method="none"``.

    Raises:
        ValueError: ``params`` is ``None`` with a method other than ``"none"`` (``"auto"`` resolves to a stretch), or
            ``params.hi`` is not greater than ``params.lo``.
    """
    config = config or EnhanceConfig()
    img16 = grey(img16)
    method = resolve_method(img16, config.method)
    if method == "none":
        return to_uint8(minmax_stretch(img16))
    if params is None:
        raise ValueError(f"enhance: method {method!r} needs the flight's StretchParams "
                         "(aerocal.enhance.stretch_params)")
    x = linear_stretch(img16, params.lo, params.hi)
    if method == "linear":
        return to_uint8(x)
    if config.quantise_first:
        x = to_uint8(x).astype(np.float32) / np.float32(255.0)
    c = config
    return to_uint8(wallis(x, c.wallis_mean, c.wallis_std, c.wallis_c, c.wallis_b, c.wallis_window))
