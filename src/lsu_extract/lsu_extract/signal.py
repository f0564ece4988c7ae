"""The laser-specific signal of a frame, computed only where the detectors look.

Laser light (671 nm) is almost pure red, white light is not (thesis 6.1.5). The signal is
``red - max(green, blue)`` for a colour frame: white and grey surfaces give ~0, the laser a
strong positive peak, reddish skin a small offset (where that maximum has clipped, the other channel:
`other_channel`). When a laser-off texture frame of the
same view is given, the signal is the rise of red between the two frames less the larger
rise of green or blue (never less than 0): ``(red - red_off) - max(green - green_off,
blue - blue_off, 0)``. A static scene cancels; the laser adds red (and the few per cent of it
that crosstalk puts into green and blue); a person moving between the two frames changes
every channel, and mostly cancels too. Mono frames have no colour, so their signal is the
intensity (minus the texture frame's, if given).

Computing the signal for a whole 640x480 frame costs several times a copy of the frame, so
`LaserSignal` computes it lazily: for a set of full rows (coarse search, fallback) or for a
window of columns per row (tracking), gathering the window pixels with one strided view.

The arithmetic runs in OpenCV: numpy reads a channel of interleaved BGR with a 3-byte stride
and cannot vectorise it. Full rows are de-interleaved with ``split`` and stay row-major, as
the full-row argmax wants them; the gathered rows and their planes live in per-thread buffers
reused from frame to frame (`workspace.scratch`), as does the fallback's signal. The tracking
windows are short (a few dozen pixels) and many (one per row): `window_columns` de-interleaves
them with one byte transpose (``cv2.transpose`` of the (n, 3 L) pixel bytes), which leaves each
channel as an (L, n) view with contiguous rows, and keeps that column-major layout, in which a
per-row peak search is a reduction over axis 0 (one vector operation per window column for all
rows at once) instead of numpy's per-row loop.
"""

from __future__ import annotations

import cv2
import numpy as np

from lsu_common.arrays import AnyArray

from .detectors import clamp as _clamp
from .image import ImageFormatError
from .workspace import scratch

RowSelection = AnyArray | slice
# `LaserSignal.may_hold_laser` with a laser-off frame: the share of min_contrast a row's largest rise must reach to
# be searched. On a simulated stop-snap scan of a head (472 frames), 1 x min_contrast lost 64 rows of the line's
# faint ends that the full search finds, 0.83 x none; 2/3 leaves room for a real sensor's noisier mean
RISE_MARGIN = 2.0 / 3.0


class LaserSignal:
    """Laser signal of one BGR (H, W, 3) or mono (H, W) uint8 frame, evaluated on demand."""

    def __init__(self, image: AnyArray, texture: AnyArray | None = None) -> None:
        """Wrap ``image`` (and optionally the laser-off ``texture`` frame of the same view).

        Raises:
            ImageFormatError: not a uint8 BGR/mono array, or the texture frame differs in shape.
        """
        if image.dtype != np.uint8 or image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] != 3):
            raise ImageFormatError(f"expected a uint8 BGR (H, W, 3) or mono (H, W) image, got {image.dtype} "
                                   f"{image.shape}; decode the buffer with lsu_extract.image.decode_image")
        if texture is not None and texture.shape != image.shape:
            raise ImageFormatError(f"texture frame {texture.shape} does not match the laser frame {image.shape}; "
                                   "use the laser-off frame of the same camera and size")
        self.image = np.ascontiguousarray(image)
        self.texture = None if texture is None else np.ascontiguousarray(texture, dtype=np.uint8)
        self.height, self.width = image.shape[:2]
        self.colour = image.ndim == 3
        self._rise_max: AnyArray | None = None  # per row: the largest rise of any channel over the laser-off frame

    def red(self, rows: RowSelection) -> AnyArray:
        """The red (or mono) channel of full ``rows``: (n, W) uint8."""
        return self.image[rows, :, 2] if self.colour else self.image[rows]

    def may_hold_laser(self, rows: AnyArray, min_contrast: float) -> AnyArray:
        """Which of ``rows`` may hold a line ``min_contrast`` above their background: (n,) bool.

        The laser adds to red, so a row where it stands ``min_contrast`` above the background has
        a red value at least that high. Rows darker than that everywhere (the background behind
        a face, the laser-off part of a frame) are skipped at the cost of one max per row, instead
        of a full-row search. Looking at every channel (not only red) keeps this one contiguous
        reduction; it only makes the test weaker, never wrong.

        With a laser-off frame the test is on the rise over it (any channel, saturated at 0): lit skin and
        background without the line rise by noise only, and are skipped too. The signal there is red's rise
        less the other channels' (`_other_rise`), so a row's mean signal sits a little below zero and its
        line a little less above it: rows whose rise reaches `RISE_MARGIN` of ``min_contrast`` are searched.
        """
        if len(rows) == 0:
            return np.zeros(0, bool)
        if self.texture is not None:
            if self._rise_max is None:  # once per frame: both searches of `extract_laser_line` ask
                self._rise_max = cv2.subtract(self.image, self.texture).reshape(self.height, -1).max(axis=1)
            return self._rise_max[rows] >= RISE_MARGIN * min_contrast
        # numpy: its uint8 max is vectorised; OpenCV's row reduction of uint8 runs ~100x slower. For
        # many rows the maximum of every row of the frame in place costs less than gathering them.
        if 4 * len(rows) > self.height:
            return self.image.reshape(self.height, -1).max(axis=1)[rows] >= min_contrast
        return self.image[rows].reshape(len(rows), -1).max(axis=1) >= min_contrast

    def rows(self, rows: RowSelection, reuse: bool = False) -> AnyArray:
        """Signal of whole ``rows`` (indices or a slice): (n, W) int16.

        int16 holds the signal exactly (-255..255) at half the bytes of float32, and numpy's
        int16 subtraction of the planes costs a third of OpenCV's conversion to float. With
        ``reuse`` the result is this thread's `scratch` buffer "signal" (for a caller done with
        it before it asks again); the gathered pixels and their planes always are.
        """
        pixels = self._gather(self.image, rows, "pixels")
        n = pixels.shape[0]
        if n == 0:
            return np.zeros((0, self.width), np.int16)
        signal = scratch("signal", (n, self.width), np.int16) if reuse else np.empty((n, self.width), np.int16)
        texture = None if self.texture is None else self._gather(self.texture, rows, "texture")
        if not self.colour:
            if texture is None:
                np.copyto(signal, pixels)
                return signal
            return np.subtract(pixels, texture, out=signal, dtype=np.int16)
        blue, green, red = self._split(pixels, "planes")
        if texture is None:
            return np.subtract(red, other_channel(green, blue), out=signal, dtype=np.int16)
        tex_blue, tex_green, tex_red = self._split(texture, "texture planes")
        np.subtract(red, tex_red, out=signal, dtype=np.int16)
        other = self._other_rise_in_place(green, blue, tex_green, tex_blue)
        return np.subtract(signal, other, out=signal, dtype=np.int16)

    @staticmethod
    def _gather(image: AnyArray, rows: RowSelection, name: str) -> AnyArray:
        """``image[rows]``, a copy in this thread's `scratch` buffer ``name``."""
        rows = np.arange(image.shape[0])[rows] if isinstance(rows, slice) else np.asarray(rows)
        # "clip" never fires on valid rows, and unlike the default mode writes straight into ``out``
        return np.take(image, rows, axis=0, out=scratch(name, (rows.size, *image.shape[1:]), np.uint8), mode="clip")

    @staticmethod
    def _split(pixels: AnyArray, name: str) -> tuple[AnyArray, AnyArray, AnyArray]:
        """The (blue, green, red) planes of contiguous (n, W, 3) pixels, in this thread's `scratch` buffer ``name``."""
        planes = scratch(name, (3, *pixels.shape[:2]), np.uint8)
        cv2.split(pixels, [planes[0], planes[1], planes[2]])  # OpenCV writes into planes of the right size
        return planes[0], planes[1], planes[2]

    def rows_clipped(self, rows: RowSelection) -> AnyArray:
        """Signal of whole ``rows``, clipped at 0: (n, W) uint8.

        What the coarse search reads: the laser is a positive peak, so the clipped signal has
        the same peaks, and uint8 arithmetic and copies cost a fraction of float32 ones.
        """
        if not self.colour:
            pixels = self.image[rows]
            if pixels.shape[0] == 0:
                return np.zeros((0, self.width), np.uint8)
            return pixels if self.texture is None else cv2.subtract(pixels, self.texture[rows])
        if self.texture is not None:
            return self.rows_laser_off(rows, 0)[0]
        # gathered first: OpenCV splits contiguous rows faster than rows strided across the frame
        pixels = self._gather(self.image, rows, "pixels")
        if pixels.shape[0] == 0:
            return np.zeros((0, self.width), np.uint8)
        blue, green, red = self._split(pixels, "planes")
        return cv2.subtract(red, other_channel(green, blue))

    def rows_laser_off(self, rows: RowSelection, every: int) -> tuple[AnyArray, AnyArray | None]:
        """With the laser-off frame: `rows_clipped` of ``rows`` and, for ``every`` > 0, the exact signal (`rows`) of
        ``rows[::every]``, both from one gather and split of each frame: ((n, W) uint8, (ceil(n / every), W) int16).

        The coarse search reads the clipped signal of its rows, and the noise estimate (`contrast_noise`) the
        unclipped signal of every few of them; the two share every plane. Rows where red fell are 0 in the clipped
        signal (saturating uint8 subtraction) exactly as where the exact signal is below 0.
        """
        assert self.texture is not None
        pixels = self._gather(self.image, rows, "pixels")
        texture = self._gather(self.texture, rows, "texture")
        n = pixels.shape[0]
        if n == 0:
            return np.zeros((0, self.width), np.uint8), (np.zeros((0, self.width), np.int16) if every else None)
        if not self.colour:
            exact = np.subtract(pixels[::every], texture[::every], dtype=np.int16) if every else None
            return cv2.subtract(pixels, texture), exact
        blue, green, red = self._split(pixels, "planes")
        tex_blue, tex_green, tex_red = self._split(texture, "texture planes")
        other = self._other_rise_in_place(green, blue, tex_green, tex_blue)
        exact = None
        if every:
            exact = np.subtract(red[::every], tex_red[::every], dtype=np.int16)
            exact -= other[::every]
        return cv2.subtract(cv2.subtract(red, tex_red, dst=red), other), exact

    def windows(self, rows: AnyArray, first_cols: AnyArray, length: int) -> tuple[AnyArray, AnyArray, AnyArray]:
        """Signal and red channel of ``length`` columns per row, starting near ``first_cols``.

        Windows that would cross the image border are shifted inside it, so every window
        has exactly ``length`` columns.

        Returns:
            (signal (n, length) float32, red (n, length) uint8, first column actually used (n,) int64).
        """
        length = min(int(length), self.width)
        first = _clamp(np.asarray(first_cols, dtype=np.int64), 0, self.width - length)
        starts = np.asarray(rows, dtype=np.int64) * self.width + first
        if starts.size == 0:
            return np.zeros((0, length), np.float32), np.zeros((0, length), np.uint8), first
        pixels = self._sliding(self.image, length)[starts]
        texture = None if self.texture is None else self._sliding(self.texture, length)[starts]
        signal, red = self._signal(pixels, texture)
        return signal, red, first

    def window_columns(self, starts: AnyArray, length: int) -> tuple[AnyArray, AnyArray]:
        """Signal and red channel of ``length`` pixels from each of ``starts``, column-major.

        ``starts`` are flat pixel indices (``row * width + first column``) of windows that lie
        inside their row (the caller has checked; this does not clamp).

        Returns:
            (signal (length, n) int16, red (length, n) uint8): entry ``[j, i]`` is pixel
            ``starts[i] + j``. int16 holds the signal exactly (-255..255) at half the bytes of
            float32; the red array may be a strided view.
        """
        pixels = self._sliding(self.image, length)[starts]
        texture = None if self.texture is None else self._sliding(self.texture, length)[starts]
        if not self.colour:
            red = cv2.transpose(pixels)
            if texture is None:
                return red.astype(np.int16), red
            return red.astype(np.int16) - cv2.transpose(texture), red
        planes = self._planes(pixels)
        red = planes[:, 2]
        if texture is None:
            # numpy: int16 - uint8 stays int16, and on these strided views it beats cv2.subtract's conversion
            return red.astype(np.int16) - other_channel(planes[:, 1], planes[:, 0]), red
        tex = self._planes(texture)
        signal = red.astype(np.int16) - tex[:, 2]
        signal -= cv2.max(cv2.subtract(planes[:, 1], tex[:, 1]), cv2.subtract(planes[:, 0], tex[:, 0]))
        return signal, red

    @staticmethod
    def _planes(pixels: AnyArray) -> AnyArray:
        """The channels of (n, L, 3) colour pixels column-major: (L, 3, n) uint8, entry [j, c, i] = pixels[i, j, c].

        One byte transpose de-interleaves: row 3 j + c of the (3 L, n) result is channel c of
        column j, so each channel ``[:, c]`` is a strided view whose rows are contiguous.
        """
        n, length = pixels.shape[:2]
        return cv2.transpose(pixels.reshape(n, 3 * length)).reshape(length, 3, n)

    @staticmethod
    def _other_rise_in_place(green: AnyArray, blue: AnyArray, tex_green: AnyArray, tex_blue: AnyArray) -> AnyArray:
        """`_other_rise` of planes the caller owns (this thread's scratch planes): written into ``green`` and ``blue``,
        returned in ``green``."""
        return cv2.max(cv2.subtract(green, tex_green, dst=green), cv2.subtract(blue, tex_blue, dst=blue), dst=green)

    @staticmethod
    def _other_rise(green: AnyArray, blue: AnyArray, texture: AnyArray) -> AnyArray:
        """max(green - green_off, blue - blue_off, 0) of (n, L) planes and their (n, L, 3) laser-off pixels, uint8."""
        tex_blue, tex_green, _ = cv2.split(texture)
        return cv2.max(cv2.subtract(green, tex_green), cv2.subtract(blue, tex_blue))

    def _sliding(self, image: AnyArray, length: int) -> AnyArray:
        # A (pixels - length + 1, length[, 3]) view whose entry k is the `length` pixels from flat
        # index k: fancy-indexing it copies one short contiguous run per row, ~20x faster than
        # gathering pixel by pixel. Built with the ndarray constructor, which costs a tenth of
        # as_strided's Python-level checks.
        count = self.height * self.width - length + 1
        if self.colour:
            return np.ndarray((count, length, 3), np.uint8, image, 0, (3, 3, 1))
        return np.ndarray((count, length), np.uint8, image, 0, (1, 1))

    def _signal(self, pixels: AnyArray, texture: AnyArray | None) -> tuple[AnyArray, AnyArray]:
        """(signal float32, red uint8) of (n, L[, 3]) pixels."""
        if not self.colour:
            if texture is not None:
                return cv2.subtract(pixels, texture, dtype=cv2.CV_32F), pixels
            return pixels.astype(np.float32), pixels
        blue, green, red = cv2.split(pixels)
        if texture is None:
            return cv2.subtract(red, other_channel(green, blue), dtype=cv2.CV_32F), red
        rise = cv2.subtract(red, cv2.extractChannel(texture, 2), dtype=cv2.CV_32F)
        return cv2.subtract(rise, self._other_rise(green, blue, texture), dtype=cv2.CV_32F), red


CLIPPED_OTHER = 255  # green or blue at this value has clipped: it no longer says how bright the surface is


def other_channel(green: AnyArray, blue: AnyArray) -> AnyArray:
    """What red is compared with where there is no laser-off frame: max(green, blue), uint8, a new array.

    Where that maximum has clipped (a bluish-white surface in daylight: blue at 255 while red and green are
    not), it bounds the surface's brightness from below only and would hide a laser on it (red - 255 <= 0
    under the line); the other, unclipped channel is taken there. Where both clip, the pixel stays 255.
    """
    most = cv2.max(green, blue)
    if int(most.max()) >= CLIPPED_OTHER:
        clipped = most >= CLIPPED_OTHER
        np.copyto(most, cv2.min(green, blue), where=clipped)
    return most


def contrast_noise(clipped: AnyArray, half: int) -> float:
    """Robust sigma [DN] of the contrast the coarse search thresholds, at every pixel of ``clipped`` rows.

    ``clipped`` is (n, W) uint8, the signal clipped at 0 (`LaserSignal.rows_clipped`): what the
    coarse search reads; or the signal itself (any integer-valued dtype) where clipping would hide
    the noise: a difference from a laser-off frame is noise around 0 everywhere. The contrast of a pixel is its height above the mean of the samples
    ``half`` px to either side; away from the few laser pixels that is what texture and noise
    give it. Its scale is 1.4826 x the median of its absolute value (a MAD: the laser pixels do
    not move it), read off a 256-bin histogram (OpenCV), which costs a fraction of a median.
    Pixel-to-pixel differences would not do: webcams smooth the picture, and their median is
    often 0 DN. Where the signal is negative (white, grey, blue surfaces) the clipped signal is
    0 and so is its contrast: no noise peak can rise there, and the estimate is lower.
    """
    if clipped.shape[0] == 0 or clipped.shape[1] <= 2 * half:
        return 0.0
    if clipped.dtype != np.uint8:
        clipped = clipped.astype(np.int16, copy=False)
    twice = cv2.subtract(cv2.add(clipped[:, half:-half], clipped[:, half:-half], dtype=cv2.CV_16S),
                         cv2.add(clipped[:, :-2 * half], clipped[:, 2 * half:], dtype=cv2.CV_16S))
    hist = cv2.calcHist([cv2.convertScaleAbs(twice)], [0], None, [256], [0, 256]).ravel()
    cumulative = np.cumsum(hist)
    return 1.4826 * 0.5 * float(np.searchsorted(cumulative, 0.5 * cumulative[-1]))
