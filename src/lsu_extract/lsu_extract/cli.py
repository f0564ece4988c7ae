"""`lsu extract IMAGE...`: offline laser line extraction, with an overlay picture and JSON output."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from lsu_common.arrays import AnyArray

from .detectors import METHODS
from .extractor import DEFAULT_METHOD, ROW_MODELS, ExtractorParams, LaserLineResult, explain_rows, extract_laser_line


def read_image(path: Path) -> AnyArray:
    """A picture file as a BGR (or mono) uint8 array.

    Raises:
        FileNotFoundError: no such file.
        ValueError: the file is not an image OpenCV can read, or not 8 bit.
    """
    if not path.is_file():
        raise FileNotFoundError(f"image '{path}' not found")
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise ValueError(f"'{path}' is not an image OpenCV can read (use PNG, JPEG, BMP, PPM or TIFF)")
    if image.dtype != np.uint8:
        raise ValueError(f"'{path}' is {image.dtype}; the extractor reads 8-bit images")
    if image.ndim == 3 and image.shape[2] == 4:
        image = cv2.cvtColor(image, cv2.COLOR_BGRA2BGR)
    return image


def draw_overlay(image: AnyArray, result: LaserLineResult) -> AnyArray:
    """The image (dimmed) with each detected centre as a dot coloured from red (low) to green (high quality)."""
    base = image if image.ndim == 3 else cv2.cvtColor(image, cv2.COLOR_GRAY2BGR)
    out = (base.astype(np.float32) * 0.6).astype(np.uint8)
    shift = 4  # cv2 drawing in 1/16 px, so the dots sit at the sub-pixel centre
    for u, v, q in zip(result.u, result.v, result.quality):  # one dot per detected row, not per pixel
        colour = (0, int(255 * q), int(255 * (1.0 - q)))
        cv2.circle(out, (int(round(float(u) * 16)), int(round(float(v) * 16))), 16, colour, -1, cv2.LINE_AA, shift)
    return out


def overlay_path(target: Path, image: Path, many: bool) -> Path:
    """Where the overlay of ``image`` goes: ``target`` itself, or ``target``'s stem + image stem for many images."""
    if not many:
        return target
    return target.with_name(f"{target.stem}_{image.stem}{target.suffix or '.png'}")


def summary(result: LaserLineResult) -> dict[str, Any]:
    """Counts and medians of a result, for people and for JSON."""
    found = len(result)
    return {
        "method": result.method, "image_width": result.image_width, "image_height": result.image_height,
        "rows_detected": found, "rows_searched": result.rows_searched,
        "rows_ambiguous": result.rows_ambiguous, "rows_saturated": result.rows_saturated,
        "median_width_px": float(np.median(result.width)) if found else None,
        "median_quality": float(np.median(result.quality)) if found else None,
    }


def describe(record: dict[str, Any]) -> str:
    """One line about one image's result."""
    head = f"{record['image']}: "
    if not record["rows_detected"]:
        line = head + f"no laser line found (method {record['method']}); try a lower --min-contrast"
    else:
        line = head + (f"{record['rows_detected']}/{record['rows_searched']} rows, method {record['method']}, "
                       f"median width {record['median_width_px']:.2f} px, {record['rows_ambiguous']} ambiguous, "
                       f"{record['rows_saturated']} saturated")
    return line + (f" -> {record['overlay']}" if "overlay" in record else "")


def cmd_extract(args: argparse.Namespace) -> int:
    """Run the extractor on each image; print a line (or JSON) per image; write overlays."""
    params = ExtractorParams(method=args.method, min_contrast=args.min_contrast, window_px=args.window)
    texture = read_image(Path(args.texture)) if args.texture else None
    records: list[dict[str, Any]] = []
    for name in args.images:
        path = Path(name)
        image = read_image(path)
        result = extract_laser_line(image, params, texture=texture)
        record = {"image": str(path), **summary(result)}
        codes, why = explain_rows(result, params, textured=texture is not None)
        if args.explain:
            record["models"] = {name: {"rows": int(np.count_nonzero(codes == ROW_MODELS.index(name))), "why": reason}
                                for name, reason in why.items()}
            if texture is not None:
                record["signal"] = "red's rise over the laser-off frame (--texture): red objects and ambient cancel"
        if args.overlay:
            target = overlay_path(Path(args.overlay), path, len(args.images) > 1)
            if not cv2.imwrite(str(target), draw_overlay(image, result)):
                raise ValueError(f"cannot write overlay '{target}' (check the folder exists and the extension)")
            record["overlay"] = str(target)
        if args.json:
            record.update({key: [round(float(x), 4) for x in getattr(result, key)]
                           for key in ("u", "v", "peak", "width", "quality")})
            if args.explain:
                record["model"] = [ROW_MODELS[int(c)] for c in codes]
        else:
            print(describe(record))
            for name, info in record.get("models", {}).items():
                print(f"  {info['rows']:5d} rows {name}: {info['why']}")
        records.append(record)
    if args.json:
        json.dump(records if len(records) > 1 else records[0], sys.stdout, indent=1)
        print()
    return 0


def register(subparsers: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `lsu extract` (the ``lsu.commands`` entry point of lsu_extract)."""
    defaults = ExtractorParams()
    p = subparsers.add_parser(
        "extract", help="find the laser line in image files (offline)",
        description="Find the laser line in each image: one sub-pixel centre per row, with peak, width (FWHM) "
                    "and quality. Prints a summary per image, or everything as JSON.")
    p.add_argument("images", nargs="+", metavar="IMAGE", help="image files (PNG, JPEG, ...)")
    p.add_argument("--method", "-m", choices=METHODS, default=DEFAULT_METHOD,
                   help=f"peak detector (default {DEFAULT_METHOD}; 'thesis' = the pixel-level baseline)")
    p.add_argument("--overlay", metavar="OUT.png",
                   help="write the image with the detected line drawn on it (several images: OUT_<name>.png)")
    p.add_argument("--json", action="store_true", help="print results as JSON (with per-row arrays)")
    p.add_argument("--explain", action="store_true",
                   help="say which model centred the rows and why (with --json: the model of every row)")
    p.add_argument("--texture", metavar="IMAGE", help="laser-off frame of the same view (signal = red difference)")
    p.add_argument("--min-contrast", type=float, default=defaults.min_contrast, metavar="DN",
                   help=f"laser signal above background to accept a row (default {defaults.min_contrast:g})")
    p.add_argument("--window", type=int, default=defaults.window_px, metavar="PX",
                   help=f"tracking window half-width, 0 = full rows (default {defaults.window_px})")
    p.set_defaults(func=cmd_extract)


def main(argv: list[str] | None = None) -> int:
    """Stand-alone entry (same as `lsu extract`)."""
    parser = argparse.ArgumentParser(prog="lsu")
    register(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["extract", *(sys.argv[1:] if argv is None else argv)])
    return int(args.func(args))
