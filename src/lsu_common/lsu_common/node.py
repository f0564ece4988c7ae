"""The console-script ``main()`` of every LSU node (init, build, spin, clean shutdown, exit code), and
`LsuNode`, the rclpy node class they derive from.

``rclpy.init`` installs rclpy's SIGINT and SIGTERM handlers: either signal ends the spin through
``KeyboardInterrupt`` or ``ExternalShutdownException``, which is a normal end (exit code 0). The
node is built inside the ``try`` (opening a simulated rig takes seconds, and a Ctrl-C meanwhile is
a normal end too); ``destroy_node()`` always runs, so each node's own safe state (laser off,
motion stopped, scan data on disk) is reached on every way out.
"""

from __future__ import annotations

import sys
import threading
from collections.abc import Callable, Sequence
from typing import Any

import rclpy
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.executors import ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import qos_policy_name_from_kind
from rclpy.subscription import Subscription

EXIT_OK = 0
EXIT_STARTUP_ERROR = 2  # the node could not start (bad parameter, busy port); the message says why


class LsuNode(Node):
    """rclpy's Node with one QoS event handler per subscription (incompatible QoS, logged) and none per publisher.

    rclpy gives every publisher and subscription two default event handlers (incompatible QoS, incompatible
    type), each a waitable that the executor adds to a new wait set at every wake-up and checks after it:
    with a dozen endpoints that work is a large share of a node's CPU at 30 frames/s. A subscription keeps
    its incompatible-QoS warning (what tells a user why their camera's best-effort images never arrive);
    a publisher's is the same mismatch, reported by the subscribing node on its side. ``event_callbacks``
    given by the caller are used as they are.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.qos_warnings: list[str] = []  # the incompatible-QoS warnings logged, newest last (bounded)

    def create_publisher(self, *args: Any, **kwargs: Any) -> Publisher:
        kwargs.setdefault("event_callbacks", PublisherEventCallbacks(use_default_callbacks=False))
        return super().create_publisher(*args, **kwargs)

    def create_subscription(self, *args: Any, **kwargs: Any) -> Subscription:
        topic = self.resolve_topic_name(str(kwargs["topic"] if "topic" in kwargs else args[1]))
        kwargs.setdefault("event_callbacks", SubscriptionEventCallbacks(
            incompatible_qos=lambda status: self._incompatible_qos(topic, status), use_default_callbacks=False))
        return super().create_subscription(*args, **kwargs)

    def _incompatible_qos(self, topic: str, status: Any) -> None:
        text = (f"{topic}: a publisher offers a QoS this subscription cannot take (policy "
                f"{qos_policy_name_from_kind(status.last_policy_kind)}); nothing it sends arrives here. Publish "
                f"it with this node's QoS (`lsu topic info {topic}` lists both sides)")
        self.qos_warnings = [*self.qos_warnings[-9:], text]
        self.get_logger().warning(text)


def run_node(make_node: Callable[[], Node], args: Sequence[str] | None = None, *,
             multi_threaded: bool = False, on_started: Callable[[Node], None] | None = None,
             startup_errors: tuple[type[BaseException], ...] = (), program: str = "") -> int:
    """Run one node until Ctrl-C, SIGTERM or an external shutdown; returns the process exit code.

    Args:
        make_node: builds the node (a class, or a closure passing ``cli_args``/overrides).
        args: ROS command-line arguments for ``rclpy.init`` (None: ``sys.argv``; ``[]`` for a
            sub-command whose own arguments are not ROS arguments).
        multi_threaded: spin with a `MultiThreadedExecutor` (nodes with blocking service callbacks).
        on_started: called with the node once it is built, before spinning (e.g. print its address).
        startup_errors: exception types that, raised while the node is built, are reported on stderr
            as ``<program>: error: <message>`` with exit code 2 instead of a traceback; other
            exceptions propagate after the clean shutdown.
        program: the name in that message (default: the node class's name).
    """
    rclpy.init(args=list(sys.argv if args is None else args))
    # before the node: a SIGTERM while the node is built shuts the context down, and nothing
    # (no executor, no guard condition) can be created in it afterwards
    executor = MultiThreadedExecutor() if multi_threaded else SingleThreadedExecutor()
    node: Node | None = None
    try:
        try:
            node = make_node()
        except startup_errors as exc:
            if not rclpy.ok():
                return EXIT_OK  # a shutdown signal came while the node was built (see below)
            print(f"{program or getattr(make_node, '__name__', 'node')}: error: {exc}", file=sys.stderr)
            return EXIT_STARTUP_ERROR
        if on_started is not None:
            on_started(node)
        executor.add_node(node)
        executor.spin()
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        if rclpy.ok():
            raise
        # the context was shut down (SIGTERM) while the node was being built: its rclpy calls
        # fail because of that, a normal end
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return EXIT_OK


def main_of(node_class: type[Node], *, multi_threaded: bool = False,
            startup_errors: tuple[type[BaseException], ...] = (), program: str = ""
            ) -> Callable[..., int]:
    """A console-script ``main(args=None)`` running ``node_class`` with `run_node`."""

    def main(args: list[str] | None = None) -> int:
        return run_node(node_class, args, multi_threaded=multi_threaded, startup_errors=startup_errors,
                        program=program)

    main.__doc__ = f"Console script running {node_class.__name__}."
    return main


class GraphClient:
    """A node in its own rclpy context, spun by a daemon thread: for libraries and tools that call the graph
    (services, actions, topics) beside whatever else the process runs, without touching the default context.

    ``close()`` shuts the context down first (the spin thread leaves its wait), then destroys the node.
    """

    def __init__(self, name: str, namespace: str = "/lsu") -> None:
        from rclpy.context import Context

        self.context = Context()
        rclpy.init(context=self.context)
        self.node = rclpy.create_node(name, namespace=namespace, context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self._spin = threading.Thread(target=self._spin_loop, name=f"{name}-spin", daemon=True)
        self._spin.start()

    def _spin_loop(self) -> None:
        while self.context.ok():
            try:
                self.executor.spin_once(timeout_sec=0.05)
            except Exception:  # the context went down under us during close()
                if self.context.ok():
                    raise
                return

    def close(self) -> None:
        """Leave the graph."""
        self.executor.shutdown(timeout_sec=1.0)
        rclpy.try_shutdown(context=self.context)
        self._spin.join(timeout=2.0)
        self.node.destroy_node()
