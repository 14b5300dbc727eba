"""The camera's noise model, for the data term's per-pixel weights: a frame in ADU is
y = gain (photons + read noise) + offset, so its variance is gain (y - offset) + (gain read_noise)^2
(Poisson photon counts, Gaussian read noise). Weighting each pixel by the inverse of that variance makes
the least-squares data term the Gaussian approximation of the Poisson-Gaussian likelihood: bright foci,
whose shot noise is large, no longer outweigh the faint ones on the haze.

The parameters come from the user ('gain=2.1,offset=100,read-noise=1.6': ADU per photoelectron, ADU,
electrons rms) or from the frame itself ('auto'): a mean-variance fit over the image's smooth parts (the
variance of pixel minus the mean of its four neighbours, binned by local mean, is linear in the mean
with slope gain)."""

from __future__ import annotations

import re
from dataclasses import asdict, dataclass

import numpy as np
from scipy.ndimage import uniform_filter

from ..errors import InputError

#: bins of local mean in the mean-variance fit, and the least pixels a bin needs
FIT_BINS = 24
FIT_MIN_PIXELS = 50
#: the weights are capped at this multiple of their median (pixels near 0 counts have a variance of the
#: read noise alone; without a cap a few dark pixels would carry the data term)
WEIGHT_CAP = 10.0


@dataclass(frozen=True)
class Camera:
    gain: float          #: ADU per photoelectron
    offset: float        #: ADU (dark level)
    read_noise: float    #: electrons rms
    source: str = "given"   #: 'given', or 'estimated' (from the frame)

    def as_dict(self) -> dict:
        return asdict(self)


def _number(key: str, text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise InputError(f"camera: {key}={text!r} is not a number") from None
    if not np.isfinite(v):
        raise InputError(f"camera: {key} must be finite, got {text!r}")
    return v


def parse_camera(spec):
    """``spec`` as a :class:`Camera`, or 'auto', or None: None/'none'; 'auto'; a dict or a text
    'gain=G,offset=O,read-noise=R' (gain required; offset and read noise default to 0)."""
    if spec is None or isinstance(spec, Camera):
        return spec
    if isinstance(spec, str):
        text = spec.strip()
        if text in ("", "none"):
            return None
        if text == "auto":
            return "auto"
        items = {}
        for part in text.split(","):
            m = re.fullmatch(r"\s*([a-z_-]+)\s*=\s*(\S+)\s*", part)
            if not m:
                raise InputError(f"camera: expected 'gain=G,offset=O,read-noise=R' or 'auto', got {spec!r}")
            items[m[1].replace("-", "_")] = m[2]
    elif isinstance(spec, dict):
        items = {str(k).replace("-", "_"): v for k, v in spec.items()}
    else:
        raise InputError(f"camera: expected None, 'auto', a dict or 'gain=..,offset=..,read-noise=..', got {spec!r}")
    unknown = sorted(set(items) - {"gain", "offset", "read_noise"})
    if unknown:
        raise InputError(f"camera: unknown {', '.join(unknown)} (known: gain, offset, read-noise)")
    if "gain" not in items:
        raise InputError("camera: the gain (ADU per photoelectron) is needed, e.g. 'gain=2.0'")
    vals = {k: _number(k, str(v)) for k, v in items.items()}
    cam = Camera(gain=vals["gain"], offset=vals.get("offset", 0.0), read_noise=vals.get("read_noise", 0.0))
    if cam.gain <= 0:
        raise InputError(f"camera: gain must be > 0 ADU per photoelectron, got {cam.gain:g}")
    if cam.read_noise < 0 or cam.offset < 0:
        raise InputError(f"camera: offset and read-noise must be >= 0, got {cam.offset:g} and {cam.read_noise:g}")
    return cam


def check_camera(cam: Camera, frame) -> None:
    """Refuse camera parameters the frame contradicts: an offset above the frame's median (most pixels
    would hold fewer than 0 photons)."""
    med = float(np.median(frame))
    if cam.offset > med:
        raise InputError(f"camera: offset {cam.offset:g} ADU is above the frame's median {med:g}: most pixels "
                         "would hold fewer than 0 photons (the offset is the dark level, below the signal)")


def estimate_camera(frame, offset: float = 0.0) -> Camera:
    """Gain and read noise from one frame (offset given, default 0: a frame whose dark level was removed):
    the variance of y - mean(4 neighbours) / 1.25, binned by the local 5 x 5 mean, robustly (median per
    bin, scaled to a variance), fitted as gain (mean - offset) + (gain read_noise)^2."""
    y = np.asarray(frame, np.float64)
    if y.ndim != 2 or min(y.shape) < 8:
        raise InputError(f"camera: 'auto' needs a 2D frame of at least 8 x 8 pixels, got shape {y.shape}")
    d = y[1:-1, 1:-1] - 0.25 * (y[:-2, 1:-1] + y[2:, 1:-1] + y[1:-1, :-2] + y[1:-1, 2:])
    m = uniform_filter(y, 5)[1:-1, 1:-1] - offset
    # smooth parts only: where the local mean changes little next to its own noise
    edges = np.unique(np.quantile(m, np.linspace(0, 1, FIT_BINS + 1)))
    means, variances, counts = [], [], []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (m >= lo) & (m < hi)
        if sel.sum() < FIT_MIN_PIXELS:
            continue
        dv = d[sel]
        # median of d^2 / 0.4549 (the median of a chi-square with 1 degree of freedom): robust to the
        # structure a bin holds; / 1.25: the variance of y from that of y - mean of 4 neighbours
        variances.append(np.median(dv * dv) / 0.45494 / 1.25)
        means.append(np.median(m[sel]))
        counts.append(sel.sum())
    if len(means) < 3:
        raise InputError("camera: 'auto' found too few smooth parts in the frame to fit the mean-variance line; "
                         "give the camera's gain, e.g. --camera gain=2.0,read-noise=1.5")
    A = np.column_stack([means, np.ones(len(means))])
    wfit = np.sqrt(counts)
    (gain, c), *_ = np.linalg.lstsq(A * wfit[:, None], np.asarray(variances) * wfit, rcond=None)
    if not (np.isfinite(gain) and gain > 0):
        raise InputError(f"camera: 'auto' fitted a gain of {gain:.3g} (not > 0): the frame does not look "
                         "photon-limited; give the camera's parameters or leave camera off")
    return Camera(gain=float(gain), offset=float(offset), read_noise=float(np.sqrt(max(c, 0.0)) / gain),
                  source="estimated")


def variance_weights(frame, cam: Camera) -> np.ndarray:
    """Each pixel's weight 1 / (gain (y - offset) + (gain read_noise)^2), the signal smoothed over 3 x 3
    pixels (the weights then do not favour the pixels that noise pushed down), scaled to median 1 and
    capped at WEIGHT_CAP."""
    s = np.maximum(uniform_filter(np.asarray(frame, np.float64), 3) - cam.offset, 0.0)
    var = cam.gain * s + (cam.gain * cam.read_noise) ** 2
    floor = max(float(np.median(var)) / WEIGHT_CAP, np.finfo(np.float64).tiny)
    w = 1.0 / np.maximum(var, floor)
    return w / float(np.median(w))


def camera_weights(frame, spec):
    """(frame minus the camera's offset, weights or None, the camera's record or None) for ``spec``."""
    cam = parse_camera(spec)
    if cam is None:
        return np.asarray(frame), None, None
    y = np.asarray(frame, np.float64)
    if cam == "auto":
        cam = estimate_camera(y)
    check_camera(cam, y)
    return y - cam.offset, variance_weights(y, cam), cam.as_dict()


__all__ = ["Camera", "parse_camera", "estimate_camera", "check_camera", "variance_weights", "camera_weights"]
