"""Colours of the viewer: the diverging map of signed distance, its legend, and the palette of octree levels.

Numpy only, so they can be tested without a browser. Signed distance is negative inside: inside is blue,
outside is red, zero is white, and the map saturates at +-scale (in the object's units).
"""

from __future__ import annotations

import html
import math

import numpy as np

# (position in [-1, 1], RGB): deep blue, blue, white, orange-red, deep red. The middle anchors sit near
# zero so that thin insides (a tenth of the scale deep) already read as blue.
_ANCHORS = np.array([-1.0, -0.3, 0.0, 0.3, 1.0])
_ANCHOR_RGB = np.array(
    [(37, 80, 160), (105, 150, 215), (247, 247, 247), (232, 128, 92), (165, 28, 40)], dtype=np.float64
)
# Signed distances are banded: every BAND_COUNT-th of the scale a thin darker line, so the field's
# spacing (and any kink of the interpolation) shows in the image.
BAND_COUNT = 5
_BAND_WIDTH = 0.08  # fraction of a band drawn dark
_BAND_SHADE = 0.86
ZERO_CONTOUR_RGB = (20, 20, 20)
MISSING_RGB = (128, 128, 128)


def diverging_rgb(distance: np.ndarray, scale: float) -> np.ndarray:
    """(..., 3) uint8 colours of signed distances: blue inside (< 0), white at 0, red outside, saturated at
    +-`scale` (> 0, the object's units), with a darker line every `scale` / BAND_COUNT; NaN is grey."""
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale must be a finite positive number of object units, got {scale!r}")
    t = np.asarray(distance, dtype=np.float32) * np.float32(1.0 / scale)
    missing = np.isnan(t)
    index = np.rint((np.clip(np.where(missing, 0.0, t), -1.0, 1.0) + 1.0) * ((_TABLE_SIZE - 1) / 2)).astype(np.intp)
    rgb = _TABLE[index]
    bands = np.abs(t) * np.float32(BAND_COUNT)
    with np.errstate(invalid="ignore"):  # NaN and infinity are on no band
        on_band = ((bands % 1.0) < _BAND_WIDTH) & (bands >= 1.0)
    rgb[on_band] = _TABLE_SHADED[index[on_band]]
    rgb[missing] = MISSING_RGB
    return rgb


def _map(t: np.ndarray) -> np.ndarray:
    """(..., 3) float32 colours of t in [-1, 1] (clipped), without bands."""
    t = np.clip(t, -1.0, 1.0)
    rgb = np.empty(t.shape + (3,), dtype=np.float32)
    for channel in range(3):
        rgb[..., channel] = np.interp(t, _ANCHORS, _ANCHOR_RGB[:, channel])
    return rgb


# The map tabulated at _TABLE_SIZE evenly spaced t in [-1, 1], plain and shaded (on a band).
_TABLE_SIZE = 2049
_TABLE = np.rint(_map(np.linspace(-1.0, 1.0, _TABLE_SIZE))).astype(np.uint8)
_TABLE_SHADED = np.rint(_map(np.linspace(-1.0, 1.0, _TABLE_SIZE)) * _BAND_SHADE).astype(np.uint8)


def auto_scale(distance: np.ndarray) -> float:
    """A colour scale for a slice that shows both sides: the deepest inside distance, but at least a
    quarter of the farthest outside one (inside is usually much thinner than the space around), rounded up
    to 1, 2 or 5 times a power of ten. 1.0 when there is nothing finite and non-zero to go by."""
    values = np.asarray(distance, dtype=np.float64)
    values = values[np.isfinite(values)]
    if values.size == 0:
        return 1.0
    return round_up(max(-float(values.min()), float(values.max()) / 4, 0.0))


def round_up(largest: float) -> float:
    """The smallest of 1, 2 or 5 times a power of ten at or above `largest` (1.0 for 0)."""
    if not largest > 0.0:
        return 1.0
    power = 10.0 ** math.floor(math.log10(largest))
    for step in (1.0, 2.0, 5.0, 10.0):
        if step * power >= largest * (1 - 1e-9):
            return step * power
    return 10.0 * power


def level_rgb(levels: np.ndarray, depth: int) -> np.ndarray:
    """(K, 3) uint8 greys for octree levels 0..depth: the coarsest black, the finest mid-grey. Grey, so
    the cells never read as a sign of the distance map."""
    fraction = np.clip(np.asarray(levels, dtype=np.float32) / max(depth, 1), 0.0, 1.0)
    grey = np.rint(20 + 120 * fraction).astype(np.uint8)
    return np.repeat(grey[:, None], 3, axis=1)


def format_distance(value: float) -> str:
    """A signed distance for a label: few digits, explicit sign, no '-0'."""
    if value == 0:
        return "0"
    return f"{value:+.3g}".replace("-", "\N{MINUS SIGN}")


def legend_html(scale: float) -> str:
    """A colour bar of the map from -`scale` to +`scale` with ticks in the object's units, as HTML."""
    positions = np.linspace(-1.0, 1.0, 9)
    stops = [
        f"rgb({r:.0f},{g:.0f},{b:.0f}) {100 * (t + 1) / 2:.1f}%" for t, (r, g, b) in zip(positions, _map(positions))
    ]
    ticks = "".join(
        f'<span style="position:absolute;left:{100 * (k + 1) / 2:.1f}%;transform:translateX({shift})">'
        f"{html.escape(format_distance(k * scale))}</span>"
        for k, shift in ((-1.0, "0"), (-0.5, "-50%"), (0.0, "-50%"), (0.5, "-50%"), (1.0, "-100%"))
    )  # the end labels stay inside the bar's width
    return (
        '<div style="font-size:0.8em;padding:0 0.9em">'
        "<div>signed distance (object units): inside &lt; 0 &lt; outside; "
        f"a line every {html.escape(format_distance(scale / BAND_COUNT).lstrip('+'))}, "
        "black at 0</div>"
        f'<div style="height:14px;margin-top:4px;border:1px solid #888;'
        f'background:linear-gradient(to right, {", ".join(stops)})"></div>'
        f'<div style="position:relative;height:1.3em">{ticks}</div>'
        "</div>"
    )
