"""The speckle limit of a laser-line rig: how well one row's line centre and one point's depth can be known.

A laser diode is coherent: on a surface rougher than the wavelength the line image is covered with
fully developed speckle, a multiplicative intensity field ``s`` with mean 1 and (for a circular
pupil) the intensity correlation ``C^2 [2 J1(v)/v]^2``, ``v = 2 pi NA' r / lambda``, where C is the
speckle contrast (1 = fully developed) and ``NA' = 1 / (2 N (1 + M))`` the image-side aperture of a
lens at f-number N and magnification M (Goodman, "Speckle Phenomena in Optics", 2007, ch. 4-5).

Two limits are reported:

- ``dorsch_px``: Dorsch, Haeusler and Herrmann, "Laser triangulation: fundamental uncertainty in
  distance measurement", Applied Optics 33(7), 1994: ``dx' = C lambda / (2 pi sin u')`` in the image,
  i.e. ``dz = C lambda / (2 pi sin u_obs sin theta)`` in depth. It holds for a spot imaged near the
  diffraction limit and is the floor for any spot.
- ``line_px``: the same speckle field acting on a line whose intensity profile across it is a
  Gaussian of sigma ``w`` (image plane) wider than a grain, centred per image row by the centre of
  mass (what sub-pixel line extractors approximate). Linearising the centroid,
  ``var = C^2 * integral((x - x0)^2 I0^2) / (integral I0)^2 * integral Cov_h``, where
  ``integral((x - x0)^2 I0^2) / (integral I0)^2 = w / (4 sqrt(pi))`` and ``Cov_h`` is the speckle
  correlation averaged over the row's height h (one pixel) and integrated across the line. For
  ``h`` much larger than a grain ``integral Cov_h = lambda^2 / (pi NA'^2 h)`` (the speckle
  correlation area over h); the function integrates it exactly (triangle weight over h). The
  result grows as sqrt(w): a wide coherent line averages more grains per row but each grain moves
  the centroid further; at ``w`` of about a grain it meets Dorsch's floor. See also Baribeau and
  Rioux, "Influence of speckle on laser range finders", Applied Optics 30(20), 1991.

Depth: a stereo pair matches the line in both cameras, whose speckle patterns are independent
(different viewing directions), so the disparity error is sqrt(2) x the line error and
``dz = z^2 / (f_px B) * sqrt(2) * line_px`` (parallel-axis approximation; verged cameras differ by a
few percent). ``dorsch_depth_mm`` is the single-camera laser triangulation form with the laser at the
rig centre (triangulation angle ``atan(B / 2 / z)``), for comparison with the literature.

No processing beats these for a single row; averaging independent rows along the line does
(speckle decorrelates over about a grain, less than a pixel at f/2).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import numpy as np
from scipy.special import j1

from lsu_common.arrays import AnyArray

__all__ = ["SpeckleLimit", "speckle_limit", "grain_diameter_m", "image_aperture", "correlation_area_m2",
           "row_correlation_integral_m"]


@dataclass(frozen=True)
class SpeckleLimit:
    """Speckle-limited standard deviations of one rig at one distance."""

    line_px: float            # line centre of one row (centre of mass), image pixels
    line_m: float             # the same at the sensor, metres
    dorsch_px: float          # Dorsch et al.'s floor (diffraction-limited spot), pixels
    depth_mm: float           # one stereo point (independent speckle in both cameras)
    dorsch_depth_mm: float    # Dorsch et al.'s laser-triangulation form, laser at the rig centre
    grain_px: float           # subjective speckle grain diameter (2.44 lambda N (1 + M)) in pixels
    pixel_contrast: float     # contrast left after averaging over one pixel (std / mean of a pixel's value)
    line_sigma_px: float      # the line's intensity sigma at the sensor, pixels

    def as_dict(self) -> dict[str, float]:
        """Plain dict (JSON)."""
        return asdict(self)


def image_aperture(f_number: float, magnification: float) -> float:
    """Image-side numerical aperture ``sin u' = 1 / (2 N (1 + M))``."""
    return 1.0 / (2.0 * f_number * (1.0 + magnification))


def grain_diameter_m(wavelength_m: float, f_number: float, magnification: float) -> float:
    """Subjective speckle grain diameter at the sensor, 2.44 lambda N (1 + M) (Airy disc diameter)."""
    return 2.44 * wavelength_m * f_number * (1.0 + magnification)


def correlation_area_m2(wavelength_m: float, na: float) -> float:
    """Integral of the intensity correlation [2 J1(v)/v]^2 over the image plane: lambda^2 / (pi NA'^2)."""
    return wavelength_m ** 2 / (math.pi * na * na)


def _airy2(r: AnyArray, k: float) -> AnyArray:
    v = k * r
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(v > 1e-9, (2.0 * j1(v) / np.where(v > 1e-9, v, 1.0)) ** 2, 1.0)
    return out


def row_correlation_integral_m(wavelength_m: float, na: float, height_m: float, blur_sigma_m: float = 0.0) -> float:
    """Integral across the line of the speckle correlation averaged over a row of ``height_m``.

    ``integral K(dy) A(dy) d(dy)``, ``K(dy) = integral [2 J1(v)/v]^2 d(dx)``, ``A`` the autocorrelation of
    the row's vertical weight: the pixel's box (a triangle ``(1 - |dy|/h)+ / h``), convolved with a
    Gaussian of ``sqrt(2) blur_sigma_m`` when an intensity blur of ``blur_sigma_m`` acts after the
    speckle (it averages neighbouring rows). Hand-written quadrature (no library integrates this
    kernel); tends to ``lambda^2 / (pi NA'^2 h)`` for ``h`` >> grain and no blur.
    """
    k = 2.0 * math.pi * na / wavelength_m
    ell = 1.0 / k
    # the Airy^2 tail falls as v^-3: integrate dx out to 400/k and add the analytic tail beyond
    xmax = 400.0 * ell
    x = np.linspace(0.0, xmax, 8001)
    reach = height_m + 6.0 * math.sqrt(2.0) * blur_sigma_m
    dy = np.linspace(0.0, reach, int(401 * reach / height_m))
    r = np.hypot(x[None, :], dy[:, None])
    K = 2.0 * np.trapezoid(_airy2(r, k), x, axis=1)
    # tail over |dx| > xmax: [2 J1(v)/v]^2 averages to 4 / (pi v^3), which integrates to 2 / (pi k^3 xmax^2) a side
    K += 4.0 / (math.pi * k ** 3 * xmax ** 2)
    A = np.clip(1.0 - dy / height_m, 0.0, None) / height_m
    if blur_sigma_m > 0:
        step = dy[1] - dy[0]
        full = np.concatenate([A[:0:-1], A])
        g = np.exp(-0.5 * (np.arange(-len(dy) + 1, len(dy)) * step / (math.sqrt(2.0) * blur_sigma_m)) ** 2)
        A = np.convolve(full, g / g.sum(), mode="same")[len(dy) - 1:]
    return float(2.0 * np.trapezoid(K * A, dy))


def pixel_contrast(wavelength_m: float, na: float, pixel_m: float) -> float:
    """Std/mean of fully developed speckle averaged over a square pixel (the 2D box-averaged correlation)."""
    k = 2.0 * math.pi * na / wavelength_m
    d = np.linspace(0.0, pixel_m, 161)
    w = 1.0 - d / pixel_m
    dx, dy = np.meshgrid(d, d)
    c = _airy2(np.hypot(dx, dy), k) * w[None, :] * w[:, None]
    var = 4.0 * np.trapezoid(np.trapezoid(c, d, axis=1), d) / (pixel_m * pixel_m)
    return float(math.sqrt(min(var, 1.0)))


def speckle_limit(wavelength_nm: float, f_number: float, focal_px: float, pixel_size_m: float, baseline_m: float,
                  distance_m: float, line_sigma_m: float, contrast: float = 1.0,
                  row_blur_px: float = 0.0) -> SpeckleLimit:
    """Speckle-limited sigma of a row's line centre [px] and of a stereo point's depth [mm].

    ``line_sigma_m``: Gaussian sigma of the laser sheet's intensity at the subject (FWHM / 2.355);
    ``contrast``: speckle contrast C (1 = fully developed on a rough surface); ``row_blur_px``: sigma
    of an intensity blur acting after the speckle (the simulated rig's Gaussian lens PSF), which
    averages neighbouring rows (0: the optics' own limit).
    """
    for name, value in (("wavelength_nm", wavelength_nm), ("f_number", f_number), ("focal_px", focal_px),
                        ("pixel_size_m", pixel_size_m), ("baseline_m", baseline_m), ("distance_m", distance_m),
                        ("line_sigma_m", line_sigma_m)):
        if not value > 0:
            raise ValueError(f"speckle_limit: {name} must be positive, got {value}")
    if not row_blur_px >= 0.0:
        raise ValueError(f"speckle_limit: row_blur_px must be >= 0, got {row_blur_px}")
    if not 0.0 <= contrast <= 1.0:
        raise ValueError(f"speckle_limit: contrast must be in [0, 1], got {contrast}")
    lam = wavelength_nm * 1e-9
    f_m = focal_px * pixel_size_m
    mag = f_m / max(distance_m - f_m, 1e-9)
    na = image_aperture(f_number, mag)
    w = line_sigma_m * mag                                   # line sigma at the sensor
    cov = row_correlation_integral_m(lam, na, pixel_size_m, row_blur_px * pixel_size_m)
    line_m = contrast * math.sqrt(w / (4.0 * math.sqrt(math.pi)) * cov)
    dorsch_m = contrast * lam / (2.0 * math.pi * na)
    line_px = line_m / pixel_size_m
    depth_mm = distance_m ** 2 / (focal_px * baseline_m) * math.sqrt(2.0) * line_px * 1000.0
    sin_u_obs = f_m / f_number / (2.0 * distance_m)
    sin_theta = math.sin(math.atan2(baseline_m / 2.0, distance_m))
    dorsch_depth_mm = contrast * lam / (2.0 * math.pi * sin_u_obs * sin_theta) * 1000.0
    return SpeckleLimit(line_px, line_m, dorsch_m / pixel_size_m, depth_mm, dorsch_depth_mm,
                        grain_diameter_m(lam, f_number, mag) / pixel_size_m,
                        contrast * pixel_contrast(lam, na, pixel_size_m), w / pixel_size_m)
