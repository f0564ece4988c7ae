"""Each detected row's own centre uncertainty, for fits that weigh rows by it (`lsu_reconstruct.laser_sheet`).

A row's centre is a position estimate on a noisy profile. For a Gaussian line of peak height ``A``
and standard deviation ``s`` (FWHM / 2.355) sampled at 1 px under white noise of ``noise`` DN, the
smallest variance any unbiased estimator reaches (Cramer-Rao) is ``noise^2 / (A^2 sum g'(x)^2)``,
with ``sum g'(x)^2 ~ sqrt(pi) / (2 s)``: ``sigma_u = (noise / A) sqrt(2 s / sqrt(pi))``. The
extractor's estimators come within a small factor of it (``efficiency``). Speckle adds a floor no
estimator removes (Dorsch, Haeusler, Herrmann 1994; `lsu_reconstruct.speckle` gives it for a rig),
added in quadrature. A clipped row's top says nothing: its centre comes from the flanks alone, hence
the factor for saturated rows.

A pure module: numpy only, no ROS.
"""

from __future__ import annotations

import math

import numpy as np

from lsu_common.arrays import AnyArray

FWHM_PER_SIGMA = 2.0 * math.sqrt(2.0 * math.log(2.0))
SATURATED_FACTOR = 2.0   # a clipped row: centred on its two flanks only


def row_sigma_px(peak: AnyArray, width: AnyArray, noise_dn: float, floor_px: float = 0.0,
                 efficiency: float = 1.5, saturated: AnyArray | None = None) -> AnyArray:
    """Estimated 1-sigma uncertainty [px] of each row's centre from its peak [DN] and FWHM [px] (the
    `LaserLineResult` fields), the frame's noise [DN] and a floor (speckle) [px]; see the module doc.

    Raises ValueError on a negative noise or floor (they are standard deviations).
    """
    if noise_dn < 0.0 or floor_px < 0.0:
        raise ValueError(f"noise_dn ({noise_dn}) and floor_px ({floor_px}) are standard deviations: give values >= 0")
    s = np.maximum(np.asarray(width, np.float64), 1.0) / FWHM_PER_SIGMA
    height = np.maximum(np.asarray(peak, np.float64), 1e-6)
    sigma = efficiency * (noise_dn / height) * np.sqrt(2.0 * s / math.sqrt(math.pi))
    if saturated is not None:
        sigma = np.where(saturated, SATURATED_FACTOR * sigma, sigma)
    return np.sqrt(sigma ** 2 + floor_px ** 2)
