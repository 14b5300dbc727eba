"""Background removal of measurements as in the CM2 paper (Fig. 5A): the slowly varying fluorescent
background is estimated by a grey opening with a disk larger than the targets and subtracted. The opening
runs on the device (:mod:`cm2cl.device.morphology`, cost independent of the disk's size); the disk must fit
across the image's longer side.

Why an opening (and not a rolling ball or a Gaussian high-pass): an opening never exceeds the image, so
the corrected image stays >= 0 and targets narrower than the disk keep their peak exactly (the opening
under a bead is the background around it); a Gaussian high-pass subtracts a blurred copy of the beads
too (dimming them and leaving negative rings), and a rolling ball is an opening with a paraboloid
footprint that needs a scale between intensity and distance the data does not give."""

from __future__ import annotations

import re

import numpy as np

from ..errors import InputError


def parse_background(text: str, pixel_um: float | None):
    """``'opening:RADIUS_UM'`` or ``'opening:RADIUSpx'`` -> radius in pixels (needs the pixel size in um
    for a radius in um)."""
    m = re.fullmatch(r"opening:([0-9.eE+-]+)(px|um)?", str(text).strip())
    if not m:
        raise InputError(f"background: expected 'model', 'none', 'opening:RADIUS_UM' or 'opening:RADIUSpx', got {text!r}")
    try:
        r = float(m.group(1))
    except ValueError as exc:
        raise InputError(f"background: {m.group(1)!r} is not a number") from exc
    if not np.isfinite(r) or r <= 0:
        raise InputError(f"background: the opening's radius must be a positive finite number, got {m.group(1)!r}")
    if m.group(2) == "px":
        return r
    if not pixel_um:
        raise InputError("background: a radius in um needs the measurement's pixel size (its TIFF has none); "
                         "give the radius in pixels, e.g. 'opening:40px'")
    return r / float(pixel_um)


def check_background_spec(text: str) -> None:
    """The syntax (and a pixel radius >= 1) of ``--background``, before any image is read."""
    r = parse_background(text, pixel_um=1.0)
    if str(text).strip().endswith("px") and r < 1:
        raise InputError(f"background: a radius of {r:g} px is smaller than a pixel (needs >= 1)")


def remove_background(img, radius_px: float, device=None):
    """(corrected, background): the grey opening of ``img`` by the octagon closest to a disk of
    ``radius_px``, and ``img`` minus it (>= 0)."""
    from ..device.morphology import disk_segments, grey_opening

    img = np.asarray(img, np.float64)
    across = 2 * np.ceil(float(radius_px)) + 1
    if across > max(img.shape):     # (an opening by a disk wider than the image is nearly a constant)
        raise InputError(f"background: an opening of radius {radius_px:g} px (a disk {across:g} px across) is larger "
                         f"than the measurement ({' x '.join(map(str, img.shape))} px); the disk must fit "
                         "across the image's longer side")
    a, b = disk_segments(radius_px)
    if not np.all(np.isfinite(img)):
        raise InputError("background: the measurement contains NaN/Inf values")
    bg = grey_opening(img, a, b, device).astype(np.float64)
    return np.maximum(img - bg, 0.0), bg
