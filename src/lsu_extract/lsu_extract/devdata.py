"""Real laser photographs with a reference of where the line is, and how to score an extractor on them.

The photographs live outside the repository, in ``<repo>/../shared/devdata`` (each folder has a
PROVENANCE.md with its licence and what is known of it); `devdata_dir` finds that folder and
`DevDataMissing` says how to get it. Three kinds of reference, none of them from an extractor:

- ``weld_laser_stripes_gk``: hand-drawn stripe masks. The images hold two stripes per column,
  which a one-line-per-row extractor must reject as ambiguous; so each labelled stripe is
  scored in a view of its own: the photograph transposed (its stripes run along rows, the
  extractor wants them across) with the other labelled stripes painted over (`weld_views`).
  The unlabelled reflections stay. Only the rows the stripe's mask covers are scored: some
  real stripe is deliberately left unlabelled (PROVENANCE.md).
- ``semiteleporter_turntable``: laser-on / laser-off pairs. A pixel is laser light where red
  rose between the two frames and green and blue did not rise as much (`laser_pixels`);
  runs of such pixels are the reference of the row. ``globe_1080p`` has one laser per frame;
  ``box_vga`` lights both lasers at once (two lines per row), so it is scored for false rows
  only.
- ``laser_photos_mit_misc``: single photographs without a laser-off frame; the reference is a
  hand-checked polyline of the line's centre with a band around it (`HAND_REFERENCES`), and
  rows where it is not clear (two pieces of line, the line fading out) are left unscored.

Scoring (`score_rows`): a detection within ``MATCH_PX`` of a reference run of its row is
correct; one in a row without laser light, or away from every run, is false; a row with a
clear reference run and no correct detection is missed. Precision without pixel truth
(`smooth_fit_residuals`): the residuals of the detections from a robust local quadratic fit
along the line; a real surface is smooth at the scale of a few rows, the noise of a centre
estimate is not.

A pure module: numpy, scipy and OpenCV, no ROS.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from scipy.signal import medfilt, savgol_filter

from lsu_common.arrays import AnyArray

WELD_FRAME_PX = 4        # weld panels: border cut off (plot frame)
MATCH_PX = 2.0           # a detection this close to a reference run (or inside it) is on the line
LASER_MIN_DN = 6.0       # on-off pairs: red rise that counts as laser light (also >= 3 noise sigmas) ...
CLEAR_MIN_DN = 25.0      # ... and a row is scored for missed rows where a run of >= 12 DN and 6 sigmas peaks this high
LASER_RED_RATIO = 2.0    # laser light raises red at least this many times more than green and blue
# Box pairs where a person walks behind the unit between the on and the off frame (PROVENANCE.md)
BOX_MOVING_PAIRS = (21, 25)


class DevDataMissing(FileNotFoundError):
    """The development photographs are not beside the repository."""


def repo_root() -> Path:
    """The repository this package is checked out in (the editable install's source tree)."""
    return Path(__file__).resolve().parents[3]


def devdata_dir(root: Path | None = None) -> Path:
    """``<repo>/../shared/devdata``, or `DevDataMissing` naming the path and what to do."""
    path = ((root or repo_root()) / ".." / "shared" / "devdata").resolve()
    if not (path / "weld_laser_stripes_gk").is_dir():
        raise DevDataMissing(f"no real development photographs at {path}: put the shared/ folder of the "
                             "project beside the repository (CI lays it there)")
    return path


def _read(path: Path, flags: int = cv2.IMREAD_COLOR) -> AnyArray:
    image = cv2.imread(str(path), flags)
    if image is None:
        raise DevDataMissing(f"cannot read {path}: the development data is incomplete; lay shared/ anew")
    return image


# ---------------------------------------------------------------- reference
@dataclass(frozen=True)
class RowReference:
    """Where the laser is in each row of an image: runs of columns (inclusive), per row.

    ``runs[v]`` lists (first, last, centre) of the laser-lit runs of row ``v`` (empty: no laser
    light there). ``clear[v]``: the row is scored for missed rows (a person sees the line
    there). ``scored[v]``: detections in the row are scored at all (False: unclear rows).
    """

    runs: tuple[tuple[tuple[float, float, float], ...], ...]
    clear: AnyArray
    scored: AnyArray


@dataclass(frozen=True)
class DevImage:
    """One real image to extract from, with its reference; ``texture`` is the laser-off frame if any."""

    name: str
    image: AnyArray
    reference: RowReference
    texture: AnyArray | None = None
    single_line: bool = True              # False: two lines per row, scored for false rows only


def _runs_of(mask_row: AnyArray, weight: AnyArray | None = None) -> list[tuple[float, float, float]]:
    cols = np.flatnonzero(mask_row)
    if cols.size == 0:
        return []
    cut = np.flatnonzero(np.diff(cols) > 1) + 1
    out = []
    for run in np.split(cols, cut):
        centre = float(run.mean()) if weight is None else float(run[np.argmax(weight[run])])
        out.append((float(run[0]), float(run[-1]), centre))
    return out


def laser_pixels(on: AnyArray, off: AnyArray, min_dn: float = LASER_MIN_DN, sigmas: float = 3.0
                 ) -> tuple[AnyArray, AnyArray]:
    """(laser mask, red rise) of a laser-on / laser-off BGR pair.

    Laser light adds red and only a little green and blue (colour crosstalk); a person or a
    shadow moving between the frames changes every channel. The threshold is the larger of
    ``min_dn`` and ``sigmas`` robust sigmas of the red difference (its median absolute deviation).
    """
    diff = on.astype(np.int16) - off.astype(np.int16)
    red = diff[..., 2]
    other = np.maximum(np.maximum(diff[..., 1], diff[..., 0]), 0)
    sigma = 1.4826 * float(np.median(np.abs(red - np.median(red))))
    level = max(min_dn, sigmas * sigma)
    mask = (red >= level) & (red >= LASER_RED_RATIO * other)
    # a lone pixel is noise or a moving edge, a laser line is at least 2 px across and continues
    mask = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_OPEN, np.ones((1, 2), np.uint8)).astype(bool)
    return mask, red


def pair_reference(on: AnyArray, off: AnyArray) -> RowReference:
    """Reference of an on/off pair, conservative both ways: any faint laser light (`laser_pixels`: 6 DN, 3
    sigmas) makes a detection correct; a row counts for missed rows only where a run of the strict mask
    (12 DN, 6 sigmas) peaks at `CLEAR_MIN_DN` or more."""
    mask, red = laser_pixels(on, off)
    strict, _ = laser_pixels(on, off, 2.0 * LASER_MIN_DN, 6.0)
    runs = tuple(tuple(_runs_of(mask[v], red[v])) for v in range(mask.shape[0]))
    rows = np.flatnonzero(strict.any(axis=1))
    clear = np.zeros(mask.shape[0], bool)
    clear[rows] = [any(red[v, int(c)] >= CLEAR_MIN_DN for _, _, c in _runs_of(strict[v], red[v])) for v in rows]
    return RowReference(runs, clear, np.ones(mask.shape[0], bool))


@dataclass(frozen=True)
class HandReference:
    """A hand-checked centre polyline of the line (image x, y per vertex), its band and the rows it covers."""

    pieces: tuple[tuple[tuple[float, float], ...], ...]   # each piece: vertices (u, v), v increasing
    band_px: float
    unclear_rows: tuple[tuple[int, int], ...]             # inclusive row ranges left unscored


# Read off the photographs: the vertices are the red maximum of the row, checked by eye on an overlay.
HAND_REFERENCES: dict[str, HandReference] = {
    # wall line, box front, floor; rows 336-371 hold the end of the wall line and the box's top edge together
    "capopaul_box_wall_crop.png": HandReference(
        pieces=(((130.0, 0.0), (128.5, 335.0)), ((210.5, 372.0), (211.0, 450.0)),
                ((214.0, 456.0), (309.0, 540.0), (321.5, 551.0))),
        band_px=4.0, unclear_rows=((336, 371), (451, 455))),
    # the line over the tape roll; below row 412 it fades out over the turntable
    "jlaserscanner_tape_roll.png": HandReference(
        pieces=(((393.0, 170.0), (406.0, 180.0), (415.0, 190.0), (421.0, 200.0), (427.0, 210.0), (431.0, 220.0),
                 (439.0, 230.0), (440.0, 240.0), (442.0, 250.0), (447.0, 260.0), (445.0, 270.0), (448.0, 280.0),
                 (451.0, 290.0), (451.0, 300.0), (449.0, 310.0), (451.0, 320.0), (448.0, 330.0), (448.0, 340.0),
                 (447.0, 350.0), (445.0, 360.0), (442.0, 370.0), (436.0, 380.0), (432.0, 390.0), (428.0, 400.0),
                 (420.0, 410.0)),),
        band_px=5.0, unclear_rows=((164, 169), (411, 464))),
}


def hand_reference(ref: HandReference, height: int) -> RowReference:
    """The `RowReference` of a hand-drawn polyline: one run of +-band around it in each covered row."""
    runs: list[tuple[tuple[float, float, float], ...]] = [() for _ in range(height)]
    clear = np.zeros(height, bool)
    for piece in ref.pieces:
        us, vs = np.array([p[0] for p in piece]), np.array([p[1] for p in piece])
        for v in range(int(np.ceil(vs[0])), int(np.floor(vs[-1])) + 1):
            if v >= height:
                break
            u = float(np.interp(v, vs, us))
            runs[v] = runs[v] + ((u - ref.band_px, u + ref.band_px, u),)
            clear[v] = True
    scored = np.ones(height, bool)
    for first, last in ref.unclear_rows:
        scored[first:last + 1] = False
    return RowReference(tuple(runs), clear & scored, scored)


def _stripe_tracks(mask: AnyArray) -> list[list[tuple[int, tuple[float, float, float]]]]:
    """Runs of ``mask`` linked down the rows into stripes: a run joins the stripe whose last run (at most
    3 rows up) has its centre within 3 px; where two stripes touch (one wide run) both lose that row."""
    tracks: list[list[tuple[int, tuple[float, float, float]]]] = []
    for v in range(mask.shape[0]):
        for run in _runs_of(mask[v]):
            if run[1] - run[0] > 12:
                continue  # stripes touching or crossing: no single centre
            near = [t for t in tracks if v - t[-1][0] <= 3 and abs(t[-1][1][2] - run[2]) <= 3.0]
            if near:
                min(near, key=lambda t: abs(t[-1][1][2] - run[2])).append((v, run))
            else:
                tracks.append([(v, run)])
    return tracks


def weld_views(image: AnyArray, mask: AnyArray, name: str) -> list[DevImage]:
    """One view per labelled stripe of a weld photograph (see the module doc): the photograph
    transposed, every other labelled stripe painted over (OpenCV inpainting); its reference is the
    stripe's rows where its mask is a single narrow run (two stripes touching, a crossing: left out)."""
    # the panels were cut from a plotted figure: up to 3 px of plot frame at each edge
    e = WELD_FRAME_PX
    image_t = np.ascontiguousarray(image.T[e:-e, e:-e])
    height, width = image_t.shape
    mask_t = np.zeros((height, width), bool)
    m = mask.T[e:-e, e:-e] > 127
    mask_t[:min(height, m.shape[0]), :min(width, m.shape[1])] = m[:height, :width]
    tracks = [t for t in _stripe_tracks(mask_t) if len(t) >= 40]
    views: list[DevImage] = []
    for k, track in enumerate(tracks):
        own = np.zeros((height, width), np.uint8)
        for v, (first, last, _) in track:
            own[v, int(first):int(last) + 1] = 1
        own = cv2.dilate(own, np.ones((5, 5), np.uint8))
        others = cv2.dilate(mask_t.astype(np.uint8), np.ones((15, 15), np.uint8)) & (1 - own)
        view = cv2.inpaint(image_t, others, 5, cv2.INPAINT_TELEA)
        runs: list[tuple[tuple[float, float, float], ...]] = [() for _ in range(height)]
        clear = np.zeros(height, bool)
        for v, run in track:
            runs[v] = (run,)
            clear[v] = True
        reference = RowReference(tuple(runs), clear, clear.copy())
        views.append(DevImage(f"{name}#{k + 1}", view, reference))
    return views


# ---------------------------------------------------------------- the sets
def weld_images(root: Path | None = None, samples: Sequence[int] | None = None) -> list[DevImage]:
    """The views of every weld photograph (`weld_views`), or of the numbered ``samples``."""
    folder = devdata_dir(root) / "weld_laser_stripes_gk"
    out: list[DevImage] = []
    paths = sorted(folder.glob("sample*_input.png"))
    if samples is not None:
        paths = [folder / f"sample{k:02d}_input.png" for k in samples]
    for path in paths:
        mask = _read(path.with_name(path.name.replace("_input", "_truemask")), cv2.IMREAD_GRAYSCALE)
        out += weld_views(_read(path, cv2.IMREAD_GRAYSCALE), mask, path.stem.replace("_input", ""))
    return out


def globe_images(root: Path | None = None) -> list[DevImage]:
    """The four one-laser frames of the globe (1920x1080) with their laser-off frame."""
    folder = devdata_dir(root) / "semiteleporter_turntable" / "globe_1080p"
    out: list[DevImage] = []
    for step in ("00", "16"):
        off = _read(folder / f"{step}-off.png")
        for side in ("left", "right"):
            on = _read(folder / f"{step}-{side}.png")
            out.append(DevImage(f"globe {step}-{side}", on, pair_reference(on, off), texture=off))
    return out


def box_images(root: Path | None = None, pairs: Sequence[int] = tuple(range(2, 32))) -> list[DevImage]:
    """The box pairs (640x480, both lasers lit: two lines per row): all 30, or the numbered ``pairs``
    (`BOX_MOVING_PAIRS`: a person walks behind between the two frames)."""
    folder = devdata_dir(root) / "semiteleporter_turntable" / "box_vga"
    out: list[DevImage] = []
    for k in pairs:
        on, off = _read(folder / f"{2 * k:02d}_on.png"), _read(folder / f"{2 * k + 1:02d}_off.png")
        out.append(DevImage(f"box pair {k}", on, pair_reference(on, off), texture=off, single_line=False))
    return out


def photo_images(root: Path | None = None) -> list[DevImage]:
    """The two single photographs with their hand-checked reference."""
    folder = devdata_dir(root) / "laser_photos_mit_misc"
    out: list[DevImage] = []
    for name, ref in HAND_REFERENCES.items():
        image = _read(folder / name)
        out.append(DevImage(name, image, hand_reference(ref, image.shape[0])))
    return out


def single_line_images(root: Path | None = None) -> list[DevImage]:
    """Every image with one line per row: weld views, globe frames, the two photographs."""
    return weld_images(root) + globe_images(root) + photo_images(root)


# ---------------------------------------------------------------- scoring
@dataclass
class RowScore:
    """Counts over scored rows of one or more images, and the smooth-fit residuals of the detections."""

    rows: int = 0            # scored rows
    clear_rows: int = 0      # rows where a person sees the line
    missed: int = 0          # clear rows without a correct detection
    false: int = 0           # detections in scored rows away from every reference run
    detections: int = 0
    whole_px: int = 0        # detections at a whole-pixel column (a flat top the estimator could not centre)
    residuals: AnyArray | None = None

    def add(self, other: RowScore) -> None:
        self.rows += other.rows
        self.clear_rows += other.clear_rows
        self.missed += other.missed
        self.false += other.false
        self.detections += other.detections
        self.whole_px += other.whole_px
        parts = [r for r in (self.residuals, other.residuals) if r is not None]
        self.residuals = np.concatenate(parts) if parts else None

    @property
    def missed_pct(self) -> float:
        return 100.0 * self.missed / max(self.clear_rows, 1)

    @property
    def false_pct(self) -> float:
        return 100.0 * self.false / max(self.rows, 1)

    @property
    def whole_pct(self) -> float:
        return 100.0 * self.whole_px / max(self.detections, 1)

    @property
    def rms_px(self) -> float:
        r = self.residuals
        return float(np.sqrt(np.mean(r ** 2))) if r is not None and r.size else float("nan")


def score_rows(dev: DevImage, v: AnyArray, u: AnyArray) -> RowScore:
    """Score detections (row ``v``, column ``u`` in ``dev.image``) against the reference (module doc)."""
    ref = dev.reference
    rows = v.astype(np.int64)
    cols = np.asarray(u, np.float64)
    correct = np.zeros(rows.size, bool)
    for i, (row, col) in enumerate(zip(rows, cols)):
        correct[i] = any(first - MATCH_PX <= col <= last + MATCH_PX for first, last, _ in ref.runs[row])
    scored = ref.scored[rows]
    found = np.zeros(ref.clear.size, bool)
    found[rows[correct]] = True
    score = RowScore(rows=int(np.count_nonzero(ref.scored)), detections=int(np.count_nonzero(scored)),
                     false=int(np.count_nonzero(scored & ~correct)),
                     whole_px=int(np.count_nonzero(scored & (cols == np.rint(cols)))))
    if dev.single_line:
        score.clear_rows = int(np.count_nonzero(ref.clear))
        score.missed = int(np.count_nonzero(ref.clear & ~found))
        keep = scored & correct
        res = smooth_fit_residuals(rows[keep].astype(np.float64), cols[keep])
        score.residuals = res[np.isfinite(res)]
    return score


def smooth_fit_residuals(v: AnyArray, u: AnyArray, window: int = 21, max_jump_px: float = 2.0,
                         outlier_px: float = 1.5, min_rows: int = 21) -> AnyArray:
    """Residuals of ``u`` from a robust smooth fit along the line, per continuous piece (NaN: not fitted).

    Pieces break where rows skip more than one row or the column jumps by more than
    ``max_jump_px`` (a silhouette, a second line). In each piece of at least ``min_rows`` rows:
    points more than ``outlier_px`` from a 9-row running median are outliers (NaN, replaced by
    the median for the fit), the rest are fitted by a local quadratic over ``window`` rows
    (Savitzky-Golay). Such a fit follows a curved surface but not per-row noise; it takes up
    ~3/window of the noise variance, which makes the RMS ~7 % low at 21 rows.
    """
    order = np.argsort(v, kind="stable")
    vs, us = v[order], u[order].astype(np.float64)
    out = np.full(vs.size, np.nan)
    cuts = np.flatnonzero((np.diff(vs) > 2) | (np.abs(np.diff(us)) > max_jump_px)) + 1
    for piece in np.split(np.arange(vs.size), cuts):
        if piece.size < max(min_rows, window):
            continue
        values = us[piece]
        median = medfilt(values, 9)
        bad = np.abs(values - median) > outlier_px
        fit = savgol_filter(np.where(bad, median, values), window, 2, mode="interp")
        res = values - fit
        res[bad] = np.nan
        out[piece] = res
    result = np.full(vs.size, np.nan)
    result[order] = out
    return result


def score_images(images: Sequence[DevImage], extract: Callable[[DevImage], tuple[AnyArray, AnyArray]]
                 ) -> RowScore:
    """Sum of `score_rows` over ``images``; ``extract(dev)`` returns the detections (v, u) of one image."""
    total = RowScore()
    for dev in images:
        v, u = extract(dev)
        total.add(score_rows(dev, v, u))
    return total

