"""`lsu batch BAGS_OR_FOLDERS... --out DIR`: an archive of scans reprocessed on Ray (see `lsu_batch.batch`)."""

from __future__ import annotations

import argparse
import sys

__all__ = ["register"]


def cmd_batch(args: argparse.Namespace) -> int:
    from .batch import SUMMARY_FILE, run_batch
    from .task import parse_steps

    steps = parse_steps(args.steps)
    launch_args = []
    for item in args.arg or []:
        name, sep, value = item.partition(":=")
        if not sep or not name:
            raise ValueError(f"launch argument '{item}' is not name:=value")
        launch_args.append((name, value))
    if args.workers is not None and args.workers < 1:
        raise ValueError("--workers must be at least 1")
    summary = run_batch(args.inputs, args.out, steps, address=args.address, workers=args.workers,
                        gallery=args.gallery, launch=args.launch, launch_args=launch_args,
                        progress=False if args.no_progress else None)
    print(summary.table())
    print(f"summary: {summary.out_dir}/{SUMMARY_FILE}")
    sys.stdout.flush()
    return 0 if summary.ok else 1


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    p = sub.add_parser(
        "batch", help="reprocess many recorded scans (bags) on Ray: locally, or on a cluster with --address",
        description="Reprocess every bag given (bag folders, .mcap/.db3 files, or folders searched for them) as "
                    "`lsu run replay` would, one Ray task per bag; each bag's files go to OUT/<scan>/ once "
                    "complete (cloud.ply, mesh files, signature), so a rerun skips finished bags and a killed run "
                    "resumes. Bad bags are listed with their reason and never stop the others. The face step "
                    "enrols every scanned face in the gallery at the end. Exit status 1 when a bag failed.")
    p.add_argument("inputs", nargs="+", metavar="BAGS_OR_FOLDERS")
    p.add_argument("--out", required=True, metavar="DIR", help="output folder (one folder per bag, summary.json)")
    p.add_argument("--steps", default="extract,match,mesh,face",
                   help="what to make: extract (laser lines; alone: lines.npz), match (points: cloud.ply), mesh "
                        "(mesh.ply/.obj, renders), face (signature, enrolled in the gallery); default: all")
    p.add_argument("--address", default=None,
                   help="Ray cluster address (host:port of its head); default: a private Ray on this machine")
    p.add_argument("--workers", type=int, default=None,
                   help="tasks at a time (default: one per core here, or the cluster's CPUs)")
    p.add_argument("--gallery", default=None, metavar="FILE", help="face gallery (default: OUT/gallery.db)")
    p.add_argument("--launch", default="replay",
                   help="launch file whose laser_extractor, stereo_matcher and face_processor (and their "
                        "parameters) process the bags (default: replay)")
    p.add_argument("--arg", action="append", metavar="NAME:=VALUE",
                   help="a launch argument, e.g. calibration_dir:=DIR (repeatable)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar (logs, CI)")
    p.set_defaults(func=cmd_batch)
