"""Shape descriptors for finding which catalogue asset a suspect derives from.

The D2 shape distribution (Osada et al. 2002): the histogram of distances
between random point pairs, divided by their median so it is invariant to
similarity transforms, and smooth enough to tolerate noise, resampling and
moderate cropping.  Pairs are drawn with a fixed seed so an asset always
gets the same descriptor.
"""

from __future__ import annotations

import numpy as np

__all__ = ["d2_descriptor", "descriptor_distance", "D2_BINS"]

D2_BINS = 32
# Pairs drawn: the histogram's sampling noise must stay below the differences
# between similar assets (with 60,000 pairs, a copy under 0.5 % noise ranked
# its own asset outside the top 3 among 50 procedural shapes of 4 families
# in 7 of 25 cases; with 500,000, in none).
_PAIRS = 500000
_RANGE = 3.0   # histogram covers [0, 3 x median distance]


def d2_descriptor(points, *, bins=D2_BINS, pairs=_PAIRS, seed=0):
    """D2 histogram of a point set, scale-normalised.

    Parameters
    ----------
    points : (n, 3) float

    Returns
    -------
    (bins,) float, sums to 1
    """
    rng = np.random.default_rng(seed)
    i = rng.integers(0, len(points), pairs)
    j = rng.integers(0, len(points), pairs)
    d = np.linalg.norm(points[i] - points[j], axis=1)
    d = d[d > 0]
    scale = np.median(d)
    hist, _ = np.histogram(d / scale, bins=bins, range=(0.0, _RANGE))
    return hist / max(hist.sum(), 1)


def descriptor_distance(a, b):
    """L1 distance between cumulative histograms (earth mover's distance in 1-D).

    Parameters
    ----------
    a : (bins,) float
    b : (k, bins) or (bins,) float

    Returns
    -------
    float or (k,) float
    """
    return np.abs(np.cumsum(np.atleast_2d(b), axis=-1) - np.cumsum(a)).sum(axis=-1).squeeze()
