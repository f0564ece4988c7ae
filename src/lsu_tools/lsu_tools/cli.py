"""The `lsu` command: one entry point, subcommands for everything a lab user does.

Every subcommand comes from the ``lsu.commands`` entry point group (a function
``register(subparsers)``), this package's own (`launch` and `run` here, graph introspection,
`doctor`, `demo`) as much as those of the other packages (`bag`, `scan`, `accuracy`, ...), so
this module imports none of them and each package registers what it offers.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from lsu_config import config_dir
from lsu_scan import rosenv


def resolve_launch_file(name: str) -> Path:
    """A path as given, else ``config/launch/NAME.launch.yaml``."""
    path = Path(name)
    if path.is_file():
        return path
    for candidate in (config_dir() / "launch" / f"{name}.launch.yaml", config_dir() / "launch" / name):
        if candidate.is_file():
            return candidate
    known = sorted(p.name.removesuffix(".launch.yaml") for p in (config_dir() / "launch").glob("*.launch.yaml"))
    raise FileNotFoundError(f"launch file '{name}' not found (neither a file nor one of: {', '.join(known)})")


def _load(args: argparse.Namespace):
    from .launch_file import load_groups, load_launch, parse_cli_arguments, select_nodes
    from .nodes_index import resolve_executable

    description = load_launch(resolve_launch_file(args.file), parse_cli_arguments(args.arguments), resolve_executable)
    groups = [g for item in (args.group or []) for g in item.split(",") if g]
    exclude = [g for item in (args.exclude or []) for g in item.split(",") if g]
    if not groups and not exclude:
        return description
    return select_nodes(description, groups, exclude, load_groups(config_dir() / "launch" / "groups.yaml"))


def cmd_launch(args: argparse.Namespace) -> int:
    from .launcher import Launcher

    description = _load(args)
    if not description.nodes:
        print(f"[lsu launch] {description.file}: no nodes to start")
        return 0
    return Launcher(description, sigint_timeout_s=args.sigint_timeout).run()


def cmd_run(args: argparse.Namespace) -> int:
    from .runner import run_in_process

    bags = [a for a in args.arguments if ":=" not in a]
    if bags:  # `lsu run replay BAG`: the bag handed to the extractor and matcher directly
        from .direct_replay import default_workers, run_direct_replay

        if len(bags) > 1:
            raise ValueError(f"one bag at a time (got {', '.join(bags)}); launch arguments are written name:=value")
        args.arguments = [a for a in args.arguments if ":=" in a]
        return run_direct_replay(_load(args), Path(bags[0]), exit_when_done=args.exit,
                                 workers=default_workers() if args.workers is None else args.workers)
    return run_in_process(_load(args), executor=args.executor)


def _selection_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--group", action="append", metavar="NAME[,NAME]",
                   help="start only these groups of config/launch/groups.yaml (rig, processing, view) or nodes "
                        "(by name); e.g. --group rig on the PC wired to the unit, --group processing on another")
    p.add_argument("--exclude", action="append", metavar="NAME[,NAME]",
                   help="leave these groups or nodes out")


def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `launch` and `run` (``lsu.commands`` entry point)."""
    p = sub.add_parser("launch", help="start the nodes of a YAML launch file, one process each",
                       description="Start every node of a ROS 2 YAML launch file as its own process. "
                                   "Ctrl-C stops them all (SIGINT, then SIGTERM, then SIGKILL).")
    p.add_argument("file", metavar="FILE|NAME", help="launch file, or NAME for config/launch/NAME.launch.yaml")
    p.add_argument("arguments", nargs="*", metavar="name:=value", help="launch arguments")
    _selection_options(p)
    p.add_argument("--sigint-timeout", type=float, default=2.5, metavar="S",
                   help="grace after SIGINT before SIGTERM (default 2.5)")
    p.set_defaults(func=cmd_launch)
    p = sub.add_parser("run", help="run the nodes of a launch file in one process",
                       description="Build every node of a launch file in this process and spin them on one "
                                   "executor. With a BAG (`lsu run replay BAG`), the bag's image pairs and scan "
                                   "events go straight to the extractor and matcher of this process (no DDS "
                                   "between them); their outputs are published as live.")
    p.add_argument("file", metavar="FILE|NAME", help="launch file, or NAME for config/launch/NAME.launch.yaml")
    p.add_argument("arguments", nargs="*", metavar="[BAG] name:=value",
                   help="a recorded scan's bag folder to process directly, and launch arguments")
    p.add_argument("--exit", action="store_true",
                   help="with a BAG: stop once the bag is processed and its scan cloud published")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="with a BAG: extract the images in N processes of their own while this one matches "
                        "and extracts what they leave (default: one per core beside this one, at most 4; 0: "
                        "all in this process); the same points either way")
    _selection_options(p)
    p.add_argument("--executor", choices=("multi", "single"), default="multi",
                   help="multi (default): callbacks on a thread pool, needed by nodes that wait inside a "
                        "callback (the scan coordinator); single: one thread, lower overhead per callback, "
                        "for graphs of processing nodes such as `replay`")
    p.set_defaults(func=cmd_run)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The `lsu` argument parser: every installed ``lsu.commands`` entry point, or, given the ``command``
    about to run, only what it takes.

    A plug-in's imports (OpenCV, rosbags, ...) are paid by every `lsu` process that loads it, the graph's
    launcher and each short command as much as the command that uses them. So with a ``command``, the
    plug-in of that name and this package's own (cheap, they import nothing heavy at registration) load
    first, and the rest only when none of them provides the command: commands named otherwise than their
    plug-in (`calibrate`, `render`, `mesh`) and those that extend another plug-in's command (``--laser``
    of `calibrate`) still get every plug-in, in the order of their names."""
    from .nodes_index import command_plugins

    parser = argparse.ArgumentParser(
        prog="lsu", description="LSU stereo laser-line scanner: launch, inspect and run the ROS 2 graph.",
        epilog="DDS stays on this machine: ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST unless you set it.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    plugins = command_plugins()
    first = [e for e in plugins if command is not None and (e.name == command or e.module.startswith(f"{__package__}."))]
    _load_plugins(sub, first)
    if command not in sub.choices:
        _load_plugins(sub, [e for e in plugins if e not in first])
    return parser


def _load_plugins(sub: argparse._SubParsersAction[argparse.ArgumentParser], entries: list) -> None:
    for entry in entries:
        try:
            entry.load()(sub)
        except Exception as exc:  # a broken plugin must not take the whole command down
            print(f"lsu: warning: subcommand plugin '{entry.name}' ({entry.value}) failed to load: {exc}",
                  file=sys.stderr)


def _command(argv: list[str]) -> str | None:
    """The subcommand ``argv`` starts with (None for `lsu`, `lsu -h ...`: they list every command)."""
    return argv[0] if argv and not argv[0].startswith("-") else None


def main(argv: list[str] | None = None) -> int:
    """Console script `lsu`."""
    from lsu_common.interrupts import accept_interrupts
    from lsu_common.o3d import defer_plotly_viewer

    try:
        accept_interrupts()  # started by a launcher: a Ctrl-C held during start-up ends it here
    except KeyboardInterrupt:
        return 130

    defer_plotly_viewer()
    report = rosenv.apply_defaults()
    argv = sys.argv[1:] if argv is None else argv
    parser = build_parser(_command(argv))
    args = parser.parse_args(argv)
    args.env_report = report  # what lsu set by default, for `lsu doctor`
    from lsu_bags.rosmsg import InterfaceError
    from lsu_scan.scanner import ScannerError

    from .graph import GraphError
    from .launch_file import LaunchError

    try:
        return int(args.func(args) or 0)
    except (LaunchError, GraphError, InterfaceError, ScannerError, LookupError, FileNotFoundError,
            ValueError) as exc:
        print(f"lsu {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(main())
