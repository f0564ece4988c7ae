"""Physics of real laser-line images for the simulated rig (pure numpy/OpenCV): speckle, skin, sensor.

Speckle. The laser is coherent: the image of a rough surface lit by it is the sum of many
random-phase wavelets passed through the lens pupil, i.e. a circular complex Gaussian field whose
amplitude correlation is the Airy pattern of the image-side aperture ``NA' = 1 / (2 N (1 + M))``.
`speckle_tiles` builds that field from first principles (white complex Gaussian scatterers, an ideal circular
pupil in the Fourier domain, ``|field|^2``, box-averaged over each pixel from ``q x q``
sub-samples that resolve the field), normalised to mean 1: the pixel-integrated speckle, whose
contrast falls below 1 when a pixel holds several grains (grain diameter ``2.44 lambda N (1 + M)``).
Each camera has its own bank of tiles (the two cameras look from different directions, so their
patterns are independent). A capture multiplies the laser irradiance by one realisation: a
tile, a row and column offset and a flip drawn from the capture's seeded generator. A new carriage
position lights a different patch of the surface microstructure (0.42 mm per step against grains
of a few micrometres on the surface), so every snap gets a new, independent realisation; within one
exposure the pattern is fixed. ``contrast`` C < 1 (partially developed speckle: surfaces smoother
than the wavelength, depolarising volume scatter) scales the fluctuation: ``1 + C (s - 1)``.

Skin. Red light enters skin and remits around its entry point: the line is the sheet profile
convolved across the line with a diffusion kernel, and under oblique incidence its centre moves
along the surface away from the laser by ``sin(alpha_t) / (mu_a + mu_s')`` (oblique-incidence
reflectometry, Wang and Jacques, Applied Optics 34(13), 1995; optical properties near 650-670 nm:
Jacques, Phys. Med. Biol. 58, 2013). `skin_profile` models the remitted part with a two-sided
exponential kernel (an exponentially modified Gaussian in closed form) plus a surface part that keeps
the sheet's own profile.

Sensor. `bloom` spills the charge above full well into the pixels above and below (a CCD's
vertical register); `mosaic` / `demosaic` give a Bayer sensor with OpenCV's demosaicing.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
import scipy.fft
from scipy.special import erf, erfc, erfcx

from lsu_common.arrays import AnyArray

__all__ = ["SpeckleModel", "SkinModel", "speckle_tiles", "SpeckleField", "skin_profile", "skin_profile_tails",
           "surface_profile_box", "skin_profile_box", "noise_window", "bloom", "BAYER_PATTERNS", "mosaic", "demosaic"]


@dataclass
class SpeckleModel:
    """Laser speckle of the rig's cameras (see the module docstring)."""

    contrast: float = 1.0          # C: 1 = fully developed (rough surface), 0 = no speckle
    tiles: int = 2                 # independent tiles per camera
    tile_cols: int = 32            # tile width [px] (> a row's line window); tiles span the image height


@dataclass
class SkinModel:
    """Subsurface scattering of the laser in skin (objects with ``material == "skin"``)."""

    diffusion_length_m: float = 0.0010     # scale b of the two-sided exponential kernel across the line
    subsurface_fraction: float = 0.9       # share of the remitted laser light that went through the tissue
    mu_s_prime_per_m: float = 1500.0       # reduced scattering coefficient (1.5 / mm)
    mu_a_per_m: float = 30.0               # absorption coefficient (0.03 / mm)
    refractive_index: float = 1.40

    @property
    def centre_shift_per_sin_t(self) -> float:
        """Shift of the remitted light's centre per sin(refraction angle) [m]: 1 / (mu_a + mu_s')."""
        return 1.0 / (self.mu_a_per_m + self.mu_s_prime_per_m)


_TILE_CACHE: dict[tuple, AnyArray] = {}


def speckle_tiles(wavelength_m: float, f_number: float, magnification: float, pixel_m: float, rows: int, cols: int,
                  count: int, seed: int) -> AnyArray:
    """``count`` pixel-integrated speckle intensity tiles (count, rows, cols), float32, mean 1 each.

    The rough surface sends a circular complex Gaussian field (many random scatterers per sample)
    through the pupil (``|f| <= NA' / lambda``); ``|field|^2`` on a grid of ``q x q`` sub-samples
    per pixel, box-averaged. ``q`` puts the pupil's cut-off below 0.95 of the sub-grid's Nyquist
    frequency: the field is resolved, and the pixel statistics agree with the closed forms of
    `lsu_reconstruct.speckle` (contrast, correlation integral) within a few percent. Periodic (FFT),
    so offsets wrap around. Cached per arguments (the tiles do not depend on the scene).
    """
    key = (round(wavelength_m * 1e12), round(f_number * 1e6), round(magnification * 1e9), round(pixel_m * 1e12),
           rows, cols, count, seed)
    if key in _TILE_CACHE:
        return _TILE_CACHE[key]
    na = 1.0 / (2.0 * f_number * (1.0 + magnification))
    kc = na / wavelength_m                                   # amplitude cut-off [cycles / m]
    q = int(min(max(math.ceil(2.0 * kc * pixel_m / 0.95), 1), 24))
    rng = np.random.default_rng(np.random.SeedSequence([0x5BEC, int(seed)]))
    fy = np.fft.fftfreq(rows * q, pixel_m / q)
    fx = np.fft.fftfreq(cols * q, pixel_m / q)
    pupil = ((fy[:, None] ** 2 + fx[None, :] ** 2) <= kc * kc).astype(np.float32)
    out = np.empty((count, rows, cols), np.float32)
    for k in range(count):
        field = np.empty((rows * q, cols * q), np.complex64)
        field.real = rng.standard_normal(field.shape, dtype=np.float32)
        field.imag = rng.standard_normal(field.shape, dtype=np.float32)
        field = scipy.fft.ifft2(scipy.fft.fft2(field, overwrite_x=True) * pupil, overwrite_x=True)
        inten = (field.real ** 2 + field.imag ** 2).reshape(rows, q, cols, q).mean(axis=(1, 3))
        out[k] = inten / inten.mean()
    out.setflags(write=False)
    if len(_TILE_CACHE) > 8:
        _TILE_CACHE.clear()
    _TILE_CACHE[key] = out
    return out


class SpeckleField:
    """One camera's speckle: draws a realisation per capture and samples it at pixels."""

    def __init__(self, model: SpeckleModel, wavelength_m: float, f_number: float, magnification: float,
                 pixel_m: float, height: int, seed: int) -> None:
        self.model = model
        self.height = height
        self.tiles = (speckle_tiles(wavelength_m, f_number, magnification, pixel_m, height, model.tile_cols,
                                    model.tiles, seed) if model.contrast > 0 else None)

    def sample(self, rows: AnyArray, cols: AnyArray, rng: np.random.Generator) -> AnyArray | None:
        """Speckle factors (mean 1) at pixels (rows, cols) for a new realisation; None when off."""
        if self.tiles is None:
            return None
        count, H, Wt = self.tiles.shape
        k = int(rng.integers(count))
        dy, dx = int(rng.integers(H)), int(rng.integers(Wt))
        flip_r, flip_c = bool(rng.integers(2)), bool(rng.integers(2))
        r = (rows + dy) % H
        c = (cols + dx) % Wt
        s = self.tiles[k, H - 1 - r if flip_r else r, Wt - 1 - c if flip_c else c]
        if self.model.contrast != 1.0:
            s = 1.0 + self.model.contrast * (s - 1.0)
        return s


_SQRT2 = math.sqrt(2.0)


def _exp_erfc(z: AnyArray, a: AnyArray, g: AnyArray) -> AnyArray:
    """``exp(a) erfc(z)`` where ``a = z^2 + log g``, without overflow.

    ``exp(a) erfc(z) = g erfcx(z)`` for z >= 0 and ``2 exp(a) - g erfcx(-z)`` for z < 0 (where ``a``
    stays moderate in every use here); the exponential is evaluated only where z < 0.
    """
    out = g * erfcx(np.abs(z))
    neg = z < 0
    ea = np.minimum(a, 700.0)
    np.exp(ea, out=ea, where=neg)
    return np.where(neg, 2.0 * ea - out, out)


@dataclass(frozen=True)
class KernelScale:
    """Per-point constants of the Gaussian (``sigma``) + two-sided exponential (``b``) kernel.

    They do not depend on the sheet's offset, so a renderer computes them once per pixel; every
    function below that takes them gives the same numbers as computing them on the spot.
    """

    sigma: AnyArray          # sqrt(s2)
    b: AnyArray              # the exponential's scale (>= 1e-9)
    rb: AnyArray             # sigma / b
    h: AnyArray              # (sigma / b)^2 / 2
    sigma_sqrt2: AnyArray    # sigma sqrt 2

    @classmethod
    def of(cls, s2: AnyArray, width_d: AnyArray) -> KernelScale:
        """From the pixel-integrated sheet variance and the kernel's length (clamped to >= 1e-9)."""
        sigma = np.sqrt(s2)
        b = np.maximum(width_d, 1e-9)
        rb = sigma / b
        return cls(sigma, b, rb, 0.5 * rb ** 2, sigma * _SQRT2)

    def take(self, sel: AnyArray) -> KernelScale:
        """The constants of the points ``sel`` (an index or mask)."""
        return KernelScale(self.sigma[sel], self.b[sel], self.rb[sel], self.h[sel], self.sigma_sqrt2[sel])


def _emg_two_sided(xs: AnyArray, xb: AnyArray, k: KernelScale) -> AnyArray:
    """Density of a Gaussian (sigma) convolved with a two-sided exponential exp(-|x|/b) / (2 b), at x.

    ``xs = x / sigma``, ``xb = x / b``. Each side is an exponentially modified Gaussian; written with erfcx
    so no term overflows: ``exp(s^2/2b^2 -+ x/b) erfc(z)`` with ``z = (s/b -+ x/s)/sqrt 2`` equals
    ``exp(-x^2/2s^2) erfcx(z)`` for z >= 0 and ``2 exp(s^2/2b^2 -+ x/b) - exp(-x^2/2s^2) erfcx(-z)`` for z < 0.
    """
    g = np.exp(-0.5 * xs ** 2)
    total = _exp_erfc((k.rb - xs) / _SQRT2, k.h - xb, g)
    total += _exp_erfc((k.rb + xs) / _SQRT2, k.h + xb, g)
    return total / (4.0 * k.b)


def _emg_two_sided_cdf(xs: AnyArray, xb: AnyArray, xq: AnyArray, k: KernelScale) -> AnyArray:
    """Distribution function of `_emg_two_sided` at x (``xs = x / sigma``, ``xb = x / b``, ``xq = x / (sigma sqrt 2)``).

    Half of the kernel is ``+E``, half ``-E`` with E exponential (rate 1/b); for a Gaussian plus
    ``+-E``: ``Phi(x/s) -+ exp(s^2/2b^2 -+ x/b) Phi(+-x/s - s/b)`` (the exponentially modified Gaussian's
    distribution function), so ``F = Phi(x/s) - exp(a1) erfc(z1) / 4 + exp(a2) erfc(z2) / 4`` with the
    ``z``, ``a`` of `_emg_two_sided`; each product through `_exp_erfc`.
    """
    g = np.exp(-0.5 * xs ** 2)
    total = 0.5 * erfc(-xq)
    total += -0.25 * _exp_erfc((k.rb - xs) / _SQRT2, k.h - xb, g)
    total += 0.25 * _exp_erfc((k.rb + xs) / _SQRT2, k.h + xb, g)
    return total


def skin_profile(d: AnyArray, s2: AnyArray, sheet_sigma_m: float, width_d: AnyArray, shift_d: AnyArray,
                 fraction: float) -> AnyArray:
    """Laser profile on skin at sheet offsets ``d`` (same normalisation as the surface profile).

    ``s2``: pixel-integrated sheet variance; ``width_d``: the diffusion length along the sheet normal;
    ``shift_d``: the remitted light's centre shift along the sheet normal. The surface profile is
    ``exp(-d^2/2 s2) * sheet_sigma / sqrt(s2)`` (integral ``sheet_sigma sqrt(2 pi)``); the remitted
    part has the same integral.
    """
    k = KernelScale.of(s2, width_d)
    surface = np.exp(-0.5 * d * d / s2) * (sheet_sigma_m / k.sigma)
    u = d - shift_d
    remitted = _emg_two_sided(u / k.sigma, u / k.b, k) * (sheet_sigma_m * math.sqrt(2.0 * math.pi))
    return (1.0 - fraction) * surface + fraction * remitted


def surface_profile_box(d_lo: AnyArray, d_hi: AnyArray, s2: AnyArray, sheet_sigma_m: float,
                        r: AnyArray | None = None) -> AnyArray:
    """The surface profile ``exp(-d^2/2 s2) sheet_sigma / sqrt(s2)`` averaged over d uniform in [d_lo, d_hi].

    A sheet moving at a constant rate during the exposure sweeps its offset uniformly over an
    interval: the exposure is this box average (closed form, erf), not a sum of sub-exposures.
    ``d_hi - d_lo`` must be > 0 (a few percent of ``sqrt(s2)`` or more keeps the difference exact).
    ``r``: ``1 / sqrt(2 s2)`` when the caller has it.
    """
    if r is None:
        r = 1.0 / np.sqrt(2.0 * s2)
    x_lo, x_hi = d_lo * r, d_hi * r
    # erf is exactly +-1 beyond ERF_ONE (float64), so an interval entirely beyond it on one side has
    # difference 0: erf is evaluated only on the others (most of a skin line's wide band)
    # (gathered, not through the ufunc's where=: scipy's special ufuncs corrupt memory with it, scipy PR 25127)
    near = np.flatnonzero((x_lo < ERF_ONE) & (x_hi > -ERF_ONE))
    diff = np.zeros_like(x_lo)
    diff[near] = erf(x_hi[near]) - erf(x_lo[near])
    return diff * (sheet_sigma_m * math.sqrt(0.5 * math.pi) / (d_hi - d_lo))


# scipy's float64 erf(x) is exactly 1.0 for x >= 6 (1 - erf(6) = 2.2e-17 is below half an ulp of 1);
# test_sim_physics checks it on a grid, so a library that rounds differently fails a test, not the images
ERF_ONE = 6.0


# Beyond TAIL_Z standard deviations past the kernel's own scale (x / sigma - sigma / b >= TAIL_Z) one
# side of `_emg_two_sided` is the plain exponential exp(sigma^2/2b^2 - |x|/b) / (2 b): the terms left out
# are below exp(-TAIL_Z^2 / 2) = 1.5e-8 of it (the erfc of the exponential side differs from 2 by
# erfc(TAIL_Z / sqrt 2), the other side and the Gaussian by exp(-z^2) relative). Most of the pixels in a
# skin line's band are in these tails: one exponential each instead of the erfcx forms.
TAIL_Z = 6.0


def _scale_of(s2: AnyArray, width_d: AnyArray | None, scale: KernelScale | None) -> KernelScale:
    """The caller's `KernelScale`, or the one of ``s2`` and ``width_d``."""
    if scale is not None:
        return scale
    if width_d is None:
        raise ValueError("the skin profile needs the kernel's length width_d (or its KernelScale)")
    return KernelScale.of(s2, width_d)


def skin_profile_tails(d: AnyArray, s2: AnyArray, sheet_sigma_m: float, width_d: AnyArray | None, shift_d: AnyArray,
                       fraction: float, scale: KernelScale | None = None) -> AnyArray:
    """`skin_profile` with the remitted part's exponential tails in their closed form (within 1.5e-8, `TAIL_Z`).

    ``scale``: the points' `KernelScale` when the caller has it (then ``width_d`` is not read).
    """
    k = _scale_of(s2, width_d, scale)
    surface = np.exp(-0.5 * d * d / s2) * (sheet_sigma_m / k.sigma)
    u = d - shift_d
    us, ub = u / k.sigma, u / k.b
    right, left = us - k.rb >= TAIL_Z, -us - k.rb >= TAIL_Z
    tail = right | left
    density = np.empty_like(u)
    core = ~tail
    density[core] = _emg_two_sided(us[core], ub[core], k.take(core))
    # the tail's exponential exp(sigma^2/2b^2 - |u|/b) / (2 b)
    bt = k.b[tail]
    density[tail] = np.exp(k.h[tail] + np.where(right[tail], -ub[tail], ub[tail])) / (2.0 * bt)
    return (1.0 - fraction) * surface + fraction * density * (sheet_sigma_m * math.sqrt(2.0 * math.pi))


def skin_profile_box(d_lo: AnyArray, d_hi: AnyArray, s2: AnyArray, sheet_sigma_m: float, width_d: AnyArray | None,
                     shift_d: AnyArray, fraction: float, scale: KernelScale | None = None,
                     r: AnyArray | None = None) -> AnyArray:
    """`skin_profile` averaged over d uniform in [d_lo, d_hi]: distribution-function differences (closed form).

    In the exponential tails (`TAIL_Z`) the difference is ``exp(sigma^2/2b^2 - |u_near|/b)
    (1 - exp(-(d_hi - d_lo)/b)) / 2`` with ``u_near`` the interval's end nearer the line.
    ``scale``, ``r``: the points' `KernelScale` and ``1 / sqrt(2 s2)`` when the caller has them.
    """
    surface = surface_profile_box(d_lo, d_hi, s2, sheet_sigma_m, r)
    k = _scale_of(s2, width_d, scale)
    u_lo, u_hi = d_lo - shift_d, d_hi - shift_d
    lo_s, hi_s = u_lo / k.sigma, u_hi / k.sigma
    right, left = lo_s - k.rb >= TAIL_Z, -hi_s - k.rb >= TAIL_Z
    tail = right | left
    core = ~tail
    mass = np.empty_like(u_lo)
    kc = k.take(core)
    ulc, uhc = u_lo[core], u_hi[core]
    mass[core] = (_emg_two_sided_cdf(hi_s[core], uhc / kc.b, uhc / kc.sigma_sqrt2, kc)
                  - _emg_two_sided_cdf(lo_s[core], ulc / kc.b, ulc / kc.sigma_sqrt2, kc))
    bt, ult, uht = k.b[tail], u_lo[tail], u_hi[tail]
    near = np.where(right[tail], -ult, uht)
    mass[tail] = 0.5 * np.exp(k.h[tail] + near / bt) * -np.expm1(-(uht - ult) / bt)
    remitted = mass * (sheet_sigma_m * math.sqrt(2.0 * math.pi) / (d_hi - d_lo))
    return (1.0 - fraction) * surface + fraction * remitted


_NOISE_BANK: dict[int, AnyArray] = {}
NOISE_BANK_SIZE = 1 << 22   # standard normal samples (16 MB); > 4 x a 640x480x3 image


def noise_window(shape: tuple[int, ...], rng: np.random.Generator) -> tuple[AnyArray, float]:
    """A window of iid standard normal samples of ``shape`` (a read-only view) and a random sign, for one capture.

    The windows come from one bank drawn once per process from a fixed seed, at an offset and with a
    sign drawn from the capture's generator (as the speckle bank does): same seed, same noise, in
    every process. Statistically the same as fresh draws for every use of an image: the samples of
    one window are distinct draws, so within a capture the noise is iid N(0, 1) (times the sign, which
    keeps N(0, 1)); two captures get the same sample at the same pixel only when their offsets are
    equal (probability ~1 / 3.3e6 per pair at 640x480x3), so a pixel's noise is independent from
    capture to capture; what two captures share are samples at pixels a fixed distance apart,
    which no per-capture or per-pixel statistic (the extractor's, the tests') can see.
    """
    count = int(np.prod(shape))
    size = max(NOISE_BANK_SIZE, 4 * count)
    bank = _NOISE_BANK.get(size)
    if bank is None:
        bank = np.random.default_rng(np.random.SeedSequence([0x4015E, size])).standard_normal(size, dtype=np.float32)
        bank.setflags(write=False)
        _NOISE_BANK.clear()
        _NOISE_BANK[size] = bank
    start = int(rng.integers(size - count + 1))
    sign = -1.0 if rng.integers(2) else 1.0
    return bank[start:start + count].reshape(shape), sign


def bloom(img: AnyArray, fraction: float) -> None:
    """Saturation with blooming, in place on an (H, W[, C]) float image in full-scale units (1 = full well).

    The charge above full well is clipped; ``fraction`` of it spills, half up and half down the
    column (a CCD's vertical transfer register; anti-blooming drains drain the rest). One pass:
    a spill that fills a neighbour is clipped by quantisation.
    """
    if fraction <= 0.0 or float(img.max()) <= 1.0:
        return
    excess = np.maximum(img - np.float32(1.0), np.float32(0.0))
    np.minimum(img, np.float32(1.0), out=img)
    excess *= np.float32(0.5 * fraction)
    img[1:] += excess[:-1]
    img[:-1] += excess[1:]


# Bayer pattern name (colours of the top-left 2x2, row-major) -> OpenCV demosaicing code to BGR.
# OpenCV names its codes after the 2x2 starting at the second row and column, hence the crossing.
BAYER_PATTERNS = {"RGGB": cv2.COLOR_BayerBG2BGR, "BGGR": cv2.COLOR_BayerRG2BGR, "GRBG": cv2.COLOR_BayerGB2BGR,
                  "GBRG": cv2.COLOR_BayerGR2BGR}
_CHANNEL = {"B": 0, "G": 1, "R": 2}


def mosaic(img: AnyArray, pattern: str) -> AnyArray:
    """The single-channel Bayer image (H, W) a colour sensor records of a BGR image (H, W, 3)."""
    out = np.empty(img.shape[:2], img.dtype)
    for k, colour in enumerate(pattern):
        r, c = divmod(k, 2)
        out[r::2, c::2] = img[r::2, c::2, _CHANNEL[colour]]
    return out


def demosaic(raw: AnyArray, pattern: str) -> AnyArray:
    """BGR uint8 from a Bayer uint8 image (OpenCV's bilinear demosaicing)."""
    return cv2.cvtColor(raw, BAYER_PATTERNS[pattern])
