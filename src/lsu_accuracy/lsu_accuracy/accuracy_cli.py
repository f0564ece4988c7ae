"""`lsu accuracy`: the thesis ch. 9 accuracy study (board poses, Gaussian table, error vs distance, smoothing).

``--sim`` renders the scans on the simulated rig (exact truth); ``--bag DIR`` replays recorded board
scans of a real (or simulated) rig, with the board's pose detected in each scan's laser-off pair as
truth (`lsu_accuracy.accuracy_bag`). Both write report.md, PNG plots and accuracy.json.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["register", "cmd_accuracy"]


def cmd_accuracy(args: argparse.Namespace) -> int:
    """Run the study and write the report; prints the headline figures."""
    from .accuracy import StudyConfig, run_study

    if args.bag:
        from lsu_cameras.calibration import BoardSpec
        from lsu_config import config_dir

        from .accuracy_bag import run_bag_study

        board = BoardSpec.parse(args.board, args.square)
        calibration = Path(args.calibration) if args.calibration else \
            config_dir() / "calibration" / "sim"
        print(f"[lsu accuracy] board scans in {args.bag}: {board.cols}x{board.rows} board, {args.square:g} mm squares, "
              f"calibration {calibration}", flush=True)
        result = run_bag_study(args.bag, calibration, board, progress=lambda s: print(f"[lsu accuracy] {s}", flush=True))
        return _finish(result, Path(args.output))
    config = StudyConfig(poses=args.poses, step=args.step, seed=args.seed,
                         calibration=Path(args.calibration) if args.calibration else None)
    config.check()  # fail on bad arguments before minutes of rendering
    print(f"[lsu accuracy] {config.poses} poses, carriage step {config.step}: rendering and reconstructing "
          f"(about {config.poses * 0.3 * (470 // config.step + 1) / 60 + 0.5:.0f} min on 2 cores)", flush=True)
    result = run_study(config, progress=lambda s: print(f"[lsu accuracy] {s}", flush=True))
    return _finish(result, Path(args.output))


def _finish(result: dict, output: Path) -> int:
    from .accuracy import write_report

    files = write_report(result, output)
    f = result["figures"]
    print(f"[lsu accuracy] {result['reference_pose']}: |bias| + 3 sigma after smoothing: ours "
          f"{f['three_sigma_mm_300_smoothed']:.3f} mm, thesis chain {f['thesis_three_sigma_mm_300']:.3f} mm (thesis quote {f['thesis_quote_mm_300']} mm)")
    if "speckle_limit_mm_300" in f:
        print(f"[lsu accuracy] point sigma at 300 mm, raw: ours {f['plane_sigma_mm_300']:.4f} mm, speckle limit "
              f"{f['speckle_limit_mm_300']:.4f} mm, ratio {f['plane_sigma_over_speckle_limit']:.2f}")
    print(f"[lsu accuracy] Gaussian table (ours): {f['gaussian_1sigma_pct']:.1f} / {f['gaussian_2sigma_pct']:.1f} / "
          f"{f['gaussian_3sigma_pct']:.1f} % within 1/2/3 sigma (normal 68.2 / 95.4 / 99.7)")
    for path in files:
        print(f"[lsu accuracy] wrote {path}")
    sys.stdout.flush()
    return 0


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `accuracy` to the `lsu` parser."""
    p = sub.add_parser("accuracy", help="accuracy study (thesis ch. 9): board poses, Gaussian table, smoothing",
                       description="Scan a flat board at several poses (200..450 mm, tilted), fit planes, and "
                                   "report point-to-plane statistics, the Gaussian table, error against distance "
                                   "and the effect of smoothing, for our chain and the thesis chain.")
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--sim", action="store_true", help="scan on the simulated rig (exact truth)")
    src.add_argument("--bag", metavar="DIR", default="",
                     help="recorded board scans: a bag folder or a folder of them (e.g. scans/), one scan per board "
                          "pose, recorded with `lsu scan --record`; truth = the board detected in the laser-off pair")
    p.add_argument("-o", "--output", default="report", metavar="DIR", help="report folder (default ./report)")
    p.add_argument("--poses", type=int, default=10, help="board poses from 200 to 450 mm (default 10, >= 3)")
    p.add_argument("--step", type=int, default=8, help="carriage steps between snaps (default 8)")
    p.add_argument("--seed", type=int, default=20261123, help="render noise seed")
    p.add_argument("--calibration", default="", metavar="DIR",
                   help="calibration folder (default config/calibration/sim, the simulated rig's true calibration; "
                        "with --bag from a real rig give its own, e.g. config/calibration/lab)")
    p.add_argument("--board", default="9x6", help="--bag: chessboard inner corners COLSxROWS (default 9x6)")
    p.add_argument("--square", type=float, default=25.0,
                   help="--bag: chessboard square size [mm] (default 25; the sim's `scene:=board` has 20)")
    p.set_defaults(func=cmd_accuracy)
