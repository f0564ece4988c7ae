"""Analytic laser-line images with known sub-pixel ground truth (tests and the benchmark).

Independent of the detectors: the truth is the analytic line centre, never a detector's
output. Each pixel integrates a Gaussian line profile over its area (exactly across the
row with the normal CDF, by 4 sub-rows down the column), then ambient light on a reddish
texture, colour crosstalk of the laser, a weaker reflection, seeded shot + read noise,
8-bit quantisation and saturation are applied, like a colour camera would.

Stand-in for the simulated rig (``lsu_sim``) until that renderer lands.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np
from scipy.special import ndtr

from lsu_common.arrays import AnyArray

FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))
_SUB_ROWS = (np.arange(4) + 0.5) / 4.0 - 0.5  # vertical sample offsets inside one pixel


@dataclass(frozen=True)
class LineScene:
    """What one synthetic camera frame shows. Units: pixels and 8-bit digital numbers (DN)."""

    width: int = 640
    height: int = 480
    u0_px: float = 320.37            # line centre at the middle row
    slope_px_per_row: float = 0.05   # du/dv: slant
    bow_px: float = 6.0              # quadratic bow: centre moves by this much at the top and bottom rows
    fwhm_px: float = 4.0             # full width at half maximum of the laser profile
    amplitude_dn: float = 160.0      # red response at the centre of the line on a white (albedo 1) surface
    leak_green: float = 0.06         # laser crosstalk into green / blue (colour filter overlap)
    leak_blue: float = 0.04
    ambient: float = 0.1             # white ambient light: a white surface reads this fraction of full scale
    textured: bool = True            # reddish skin-like albedo with blotches; else a uniform reddish grey
    read_noise_dn: float = 1.0       # sensor read noise (sigma)
    shot_gain: float = 0.05          # shot noise variance per DN of signal
    reflection: float = 0.0          # amplitude of a second (reflected) line, as a fraction of the main one
    reflection_offset_px: float = 70.0
    first_row: int = 0               # the laser is visible in rows first_row..last_row (inclusive)
    last_row: int = -1               # -1 = the last image row
    seed: int = 0                    # noise (and reflection-free rendering is otherwise deterministic)
    texture_seed: int = 0            # the background texture: keep it for a laser-off frame of the same view

    def with_(self, **changes: object) -> LineScene:
        """A copy with some fields changed."""
        return replace(self, **changes)  # type: ignore[arg-type]


def line_centre(scene: LineScene, v: AnyArray) -> AnyArray:
    """Analytic centre column of the line at (possibly fractional) row ``v``."""
    half = scene.height / 2.0
    t = (np.asarray(v, dtype=np.float64) - half) / half
    return scene.u0_px + scene.slope_px_per_row * (v - half) + scene.bow_px * t * t


def _profile(centres: AnyArray, cols: AnyArray, sigma: float) -> AnyArray:
    """Gaussian of unit peak integrated over each pixel's width, averaged over the sub-rows.

    ``centres`` is (rows, sub_rows); result (rows, cols). Normalised so a pixel centred on the
    line reads 1, whatever the width.
    """
    norm = 1.0 / (ndtr(0.5 / sigma) - ndtr(-0.5 / sigma))
    d = cols[None, None, :] - centres[:, :, None]
    area = ndtr((d + 0.5) / sigma) - ndtr((d - 0.5) / sigma)
    return norm * area.mean(axis=1)


def _albedo(scene: LineScene, rng: np.random.Generator) -> AnyArray:
    """Reddish background reflectance (H, W, 3) in BGR, values 0..1."""
    base = np.array([0.45, 0.55, 0.85])  # skin-like: red reflects most
    shape = (scene.height, scene.width)
    if not scene.textured:
        return np.broadcast_to(base, shape + (3,)).copy()
    smooth = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), 12.0)
    smooth *= 0.18 / max(float(smooth.std()), 1e-6)
    fine = rng.standard_normal(shape).astype(np.float32) * 0.03
    # blotches: small redder patches (freckles, lips, blemishes) that a red threshold alone mistakes for laser
    blot = np.zeros(shape, np.float32)
    for _ in range(40):
        y, x = int(rng.integers(0, shape[0])), int(rng.integers(0, shape[1]))
        cv2.circle(blot, (x, y), int(rng.integers(3, 12)), float(rng.uniform(0.1, 0.3)), -1)
    blot = cv2.GaussianBlur(blot, (0, 0), 2.0)
    albedo = base[None, None, :] * (1.0 + smooth[..., None] + fine[..., None])
    albedo[..., 0] -= blot * 0.5  # redder = less blue and green
    albedo[..., 1] -= blot * 0.5
    return np.clip(albedo, 0.0, 1.0)


def render_line(scene: LineScene) -> tuple[AnyArray, AnyArray, AnyArray]:
    """Draw one frame of ``scene``.

    Returns:
        (bgr uint8 (H, W, 3), true centre column per row (H,) float64, visible (H,) bool).
        The true centre is the analytic line centre averaged over the row's vertical extent
        (exactly the centroid of the drawn profile); rows outside first_row..last_row have
        no laser (visible False).
    """
    rng = np.random.default_rng(scene.seed)
    h, w = scene.height, scene.width
    rows = np.arange(h, dtype=np.float64)
    sub = rows[:, None] + _SUB_ROWS[None, :]
    centres = line_centre(scene, sub)
    truth = centres.mean(axis=1)
    last = h - 1 if scene.last_row < 0 else scene.last_row
    visible = (rows >= scene.first_row) & (rows <= last)
    cols = np.arange(w, dtype=np.float64)
    sigma = scene.fwhm_px / FWHM_PER_SIGMA
    laser = _profile(centres, cols, sigma)
    if scene.reflection > 0.0:
        # a reflection is a blurred, weaker copy of the line somewhere else on the surface
        laser += scene.reflection * _profile(centres + scene.reflection_offset_px, cols, 1.5 * sigma)
    laser *= visible[:, None]
    albedo = _albedo(scene, np.random.default_rng([scene.texture_seed, 7919]))
    light = np.empty((h, w, 3))
    laser_dn = scene.amplitude_dn * laser * albedo[..., 2] / 0.85  # laser reflects off the same skin
    light[..., 2] = scene.ambient * 255.0 * albedo[..., 2] + laser_dn
    light[..., 1] = scene.ambient * 255.0 * albedo[..., 1] + scene.leak_green * laser_dn
    light[..., 0] = scene.ambient * 255.0 * albedo[..., 0] + scene.leak_blue * laser_dn
    sigma_dn = np.sqrt(scene.read_noise_dn ** 2 + scene.shot_gain * np.maximum(light, 0.0))
    noisy = light + rng.standard_normal(light.shape) * sigma_dn
    image = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
    return image, truth, visible
