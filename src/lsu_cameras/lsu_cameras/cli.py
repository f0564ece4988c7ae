"""`lsu calibrate` (registered through the ``lsu.commands`` entry point)."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

# OpenCV (calib_io, calibration) is imported when `lsu calibrate` runs, not by every `lsu` command


def cmd_calibrate(args: argparse.Namespace) -> int:
    """Calibrate from a folder of pairs and write left/right/stereo.yaml (nothing on failure)."""
    from .calib_io import write_calibration_dir
    from .calibration import BoardSpec, CalibrationError, calibrate_stereo, load_pairs

    if getattr(args, "live", False):
        if args.pairs:
            raise CalibrationError("give either --live or --pairs DIR, not both")
        return cmd_calibrate_live(args)
    if not args.pairs:
        raise CalibrationError("give --pairs DIR (leftNN/rightNN or left_NN/right_NN images, or left/ + right/ "
                               "sub-folders) or --live")
    board = BoardSpec.parse(args.board, args.square)
    folder = load_pairs(args.pairs)
    for line in folder.report():
        print(line, file=sys.stderr)
    result = calibrate_stereo(folder.pairs, board, min_views=args.min_views)
    write_calibration_dir(args.output, result.left, result.right, result.stereo,
                          header=f"lsu calibrate --pairs {args.pairs} --board {args.board} --square {args.square}\n"
                                 + result.summary().splitlines()[0])
    print(result.summary())
    print(f"wrote {Path(args.output) / 'left.yaml'}, right.yaml, stereo.yaml")
    return 0


def cmd_calibrate_live(args: argparse.Namespace) -> int:
    """Guided calibration from the running camera node; writes left/right/stereo.yaml when it calibrates."""
    from .calib_io import write_calibration_dir
    from .calibration import BoardSpec, CalibrationError
    from .live import CaptureClient, CoverageTracker, run_live_calibration

    board = BoardSpec.parse(args.board, args.square)
    views = getattr(args, "views", 12)
    max_views = getattr(args, "max_views", None)
    interval = getattr(args, "interval", 1.0)
    for name, value in (("--views", views), ("--min-views", args.min_views)):
        if value < 1:
            raise CalibrationError(f"{name} {value} must be at least 1")
    if max_views is not None and max_views < 1:
        raise CalibrationError(f"--max-views {max_views} must be at least 1")
    if interval < 0:
        raise CalibrationError(f"--interval {interval} must not be negative")
    tracker = CoverageTracker(board, min_views=views)
    print(f"live calibration: {board.cols}x{board.rows} board, {board.square_m * 1000:g} mm squares; move the board "
          f"across the image, nearer and farther, tilted; stops after >= {views} views with full coverage "
          "(Ctrl-C to stop early)", flush=True)
    with CaptureClient(namespace=getattr(args, "namespace", "/lsu")) as client:
        print(f"capturing from {client.service} every {interval:g} s", flush=True)
        live = run_live_calibration(client.capture, tracker, interval_s=interval, max_captures=max_views,
                                    min_views=args.min_views, save_dir=getattr(args, "save_pairs", None),
                                    report=lambda line: print(line, flush=True))
    result = live.calibration
    assert result is not None  # run_live_calibration raises when it cannot calibrate
    command = (f"lsu calibrate --live --board {args.board} --square {args.square}: {len(live.views)} views in "
               f"{live.captures} captures, stopped by {live.stopped_by}")
    write_calibration_dir(args.output, result.left, result.right, result.stereo,
                          header=command + "\n" + result.summary().splitlines()[0])
    print(result.summary())
    print(f"wrote {Path(args.output) / 'left.yaml'}, right.yaml, stereo.yaml")
    return 0


def register(subparsers: Any) -> None:
    """Add `calibrate` to the `lsu` command."""
    p = subparsers.add_parser("calibrate", help="stereo calibration from chessboard pairs",
                              description="Calibrate both cameras and their extrinsics from chessboard pairs "
                                          "(--pairs DIR: leftNN/rightNN, left_NN/right_NN or left/ + right/ folders) or "
                                          "guided from the running camera node (--live); writes left.yaml, right.yaml "
                                          "(with the pair's rectification) and stereo.yaml.")
    p.add_argument("--pairs", metavar="DIR", help="folder of leftNN/rightNN or left_NN/right_NN images (any format "
                   "OpenCV reads), or with left/ and right/ sub-folders")
    p.add_argument("--board", default="9x6", help="inner corners COLSxROWS (default 9x6)")
    p.add_argument("--square", type=float, default=25.0, help="square size [mm] (default 25)")
    p.add_argument("--min-views", type=int, default=8, help="fewest usable pairs (default 8)")
    p.add_argument("--live", action="store_true",
                   help="guided capture from the running camera node (/lsu/stereo/capture)")
    p.add_argument("--views", type=int, default=12,
                   help="--live: views needed besides full X/Y/size/skew coverage before it stops (default 12)")
    p.add_argument("--interval", type=float, default=1.0,
                   help="--live: pause between captures to move the board [s] (default 1)")
    p.add_argument("--max-views", type=int, default=None, metavar="M",
                   help="--live: stop after M captures even if coverage is incomplete (default: no limit)")
    p.add_argument("--save-pairs", metavar="DIR",
                   help="--live: keep the accepted pairs as left_NNN.png/right_NNN.png (reusable with --pairs)")
    p.add_argument("-o", "--output", default="calibration", help="output directory (default ./calibration)")
    p.set_defaults(func=_guard(cmd_calibrate))


def _guard(func: Any) -> Any:
    """Turn this package's expected errors into the one-line errors `lsu` prints (ValueError family)."""

    def run(args: argparse.Namespace) -> int:
        from .calibration import CalibrationError

        try:
            return func(args)
        except CalibrationError as exc:
            print(f"lsu {args.command}: error: {exc}", file=sys.stderr)
            return 2

    return run
