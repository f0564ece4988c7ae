"""`lsu run`: the nodes of a launch file in one process on one executor (multi-threaded by default).

Same launch files, same names, parameters and remappings as `lsu launch` (each node gets
the `--ros-args` list as node-local arguments), minus process isolation: faster start-up,
no serialization between nodes, and the easiest way to run the whole graph in a test.
"""

from __future__ import annotations

import contextlib
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any, TextIO

from .launch_file import LaunchDescription
from .nodes_index import node_class


def build_nodes(description: LaunchDescription, param_dir: Path, context: Any | None = None,
                out: TextIO | None = None) -> list[Any]:
    """Instantiate every node of ``description`` in this process (rclpy must be initialised).

    Raises:
        LookupError: a node has no in-process entry point.
    """
    out = sys.stdout if out is None else out  # the stream of the call, not of the import
    nodes: list[Any] = []
    try:
        for index, spec in enumerate(description.nodes):
            cls = node_class(spec.package, spec.executable)
            inline = None
            if spec.params:
                inline = param_dir / f"{index:02d}-{spec.label}.params.yaml"
                inline.write_text(spec.inline_params_yaml())
            if spec.args or spec.env:
                out.write(f"[lsu run] {spec.label}: 'args' and 'env' apply to separate processes only; "
                          "ignored here (use lsu launch)\n")
            kwargs: dict = {"cli_args": spec.ros_args(inline)}
            if context is not None:
                kwargs["context"] = context
            nodes.append(cls(**kwargs))
            out.write(f"[lsu run] created {spec.label} ({spec.package}/{spec.executable})\n")
    except BaseException:
        for node in nodes:
            node.destroy_node()
        raise
    return nodes


@contextlib.contextmanager
def spinning_nodes(description: LaunchDescription, out: TextIO | None = None,
                   executor: str = "multi") -> Iterator[tuple[list[Any], Any]]:
    """rclpy, every node of ``description`` and an executor holding them, for the ``with`` block.

    A Ctrl-C / SIGTERM inside the block ends it quietly; on every way out the executor stops, the
    nodes are destroyed and rclpy shut down.
    """
    out = sys.stdout if out is None else out
    import rclpy
    from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor

    from lsu_common.node import close_nodes

    rclpy.init()
    # before the nodes, as `run_node` does: a signal while they are built leaves a context nothing can be made in
    spinner = MultiThreadedExecutor() if executor == "multi" else SingleThreadedExecutor()
    nodes: list[Any] = []
    try:
        with tempfile.TemporaryDirectory(prefix="lsu-run-") as tmp:
            nodes = build_nodes(description, Path(tmp), out=out)
            for node in nodes:
                spinner.add_node(node)
            try:
                yield nodes, spinner
            except (KeyboardInterrupt, ExternalShutdownException):
                pass
    finally:
        close_nodes(spinner, nodes)  # the callbacks still running end before the nodes go


def run_in_process(description: LaunchDescription, out: TextIO | None = None, executor: str = "multi") -> int:
    """Build all nodes and spin them until Ctrl-C / SIGTERM; returns the exit code.

    ``executor``: "multi" (a thread pool: nodes may block in a callback waiting for another
    node's reply) or "single" (one thread: no hand-off between threads per callback, so a
    pipeline of processing nodes runs faster; a callback that waits would deadlock it).
    """
    out = sys.stdout if out is None else out
    from lsu_common.node import spin_until_shutdown

    with spinning_nodes(description, out, executor) as (nodes, spinner):
        out.write(f"[lsu run] spinning {len(nodes)} node(s) in one process ({executor}-threaded executor); "
                  "Ctrl-C stops\n")
        out.flush()
        spin_until_shutdown(spinner)
    out.write("[lsu run] stopped\n")
    return 0
