"""Error metric of the project (docs/CONVENTIONS.md), defined once for every script and test."""
import numpy as np


def relmse_map(img, ref):
    """The relMSE terms (I - R)^2 / (R^2 + 0.01) per pixel and channel, in float64."""
    img = np.asarray(img, np.float64)
    ref = np.asarray(ref, np.float64)
    return (img - ref) ** 2 / (ref ** 2 + 0.01)


def relmse(img, ref):
    """relMSE = mean over pixels and channels of (I - R)^2 / (R^2 + 0.01), in float64."""
    return float(np.mean(relmse_map(img, ref)))
