"""Colours of the recording: one per cluster, and a blue-to-red ramp for scales and errors."""

from __future__ import annotations

import colorsys

import numpy as np

GREY = (128, 128, 128)


def cluster_color(k: int) -> tuple[int, int, int]:
    """A distinct, stable colour per cluster id (golden-ratio hue steps)."""
    r, g, b = colorsys.hsv_to_rgb((k * 0.618033988749895) % 1.0, 0.75, 0.95)
    return int(255 * r), int(255 * g), int(255 * b)


def ramp(values: np.ndarray, low: float, high: float) -> np.ndarray:
    """``(N, 3)`` uint8: blue at ``low`` through cyan, green and yellow to red at ``high``
    (values outside are clipped)."""
    v = np.asarray(values, dtype=np.float64)
    span = high - low if high > low else 1.0
    t = np.clip((v - low) / span, 0.0, 1.0)
    hue = (1.0 - t) * (2.0 / 3.0)  # 240 degrees (blue) .. 0 (red)
    h6 = hue * 6.0
    x = 1.0 - np.abs(np.mod(h6, 2.0) - 1.0)
    sector = np.minimum(h6.astype(np.int64), 5)
    rgb = np.zeros((len(v), 3))
    # per hue sector: the channels that get the full value, the rising/falling one and zero
    table = [(0, 1, 2), (1, 0, 2), (1, 2, 0), (2, 1, 0), (2, 0, 1), (0, 2, 1)]
    for s, (ci, xi, zi) in enumerate(table):
        m = sector == s
        rgb[m, ci], rgb[m, xi], rgb[m, zi] = 1.0, x[m], 0.0
    return np.round(rgb * 255).astype(np.uint8)
