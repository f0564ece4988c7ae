"""The console-script ``main()`` of every LSU node (init, build, spin, clean shutdown, exit code), and
`LsuNode`, the rclpy node class they derive from.

``rclpy.init`` installs rclpy's SIGINT and SIGTERM handlers: either signal ends the spin through
``KeyboardInterrupt`` or ``ExternalShutdownException``, which is a normal end (exit code 0). A node run with
``defer_signals`` (`run_node`) has its own handlers instead: the signal ends the spin and the context stays up
until the nodes are destroyed. The
node is built inside the ``try`` (opening a simulated rig takes seconds, and a Ctrl-C meanwhile is
a normal end too); ``destroy_node()`` always runs, so each node's own safe state (laser off,
motion stopped, scan data on disk) is reached on every way out.

The way out has one order (`close_nodes`, also `lsu run`'s): the executor takes no new work, the
callbacks its threads still run end, then the nodes are destroyed, then the context is shut down.
A node destroyed, or a context shut down, under a running callback fails that callback's remaining
work (a reply, the laser off, a file) on destroyed handles, and tears the middleware down under a
thread still inside it.
"""

from __future__ import annotations

import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import rclpy
from rclpy.event_handler import PublisherEventCallbacks, SubscriptionEventCallbacks
from rclpy.executors import Executor, ExternalShutdownException, MultiThreadedExecutor, SingleThreadedExecutor
from rclpy.node import Node
from rclpy.publisher import Publisher
from rclpy.qos import qos_policy_name_from_kind
from rclpy.subscription import Subscription

from .interrupts import accept_interrupts

EXIT_OK = 0
EXIT_STARTUP_ERROR = 2  # the node could not start (bad parameter, busy port); the message says why
# how long a way out waits for the callbacks still running (a scan's end, a mesh being written) before the nodes
# go: below `lsu launch`'s SIGINT grace (2.5 s), so that a node that ends in time is not SIGTERMed
CALLBACK_GRACE_S = 2.0
# how often a spin (`spin_until_shutdown`) looks whether a signal came or the context was shut down
SIGNAL_POLL_S = 0.1


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

    def begin_shutdown(self) -> None:
        """The process is stopping: callbacks still running should end now (`close_nodes` calls it first, then
        waits `CALLBACK_GRACE_S` for them). Nothing by default."""

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
             startup_errors: tuple[type[BaseException], ...] = (), program: str = "",
             defer_signals: bool = False) -> int:
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
        defer_signals: SIGINT and SIGTERM, once the node is built, only end the spin (polled every
            `SIGNAL_POLL_S`); the context stays up until the nodes are destroyed. rclpy's own handlers shut the
            context down from their thread the moment the signal comes, under whatever a callback thread is
            doing in the middleware: a node whose callbacks spin an executor of their own (scan_coordinator's
            scan thread) ended in SIGSEGV inside that wait on Ctrl-C mid-scan.
    """
    from .o3d import defer_plotly_viewer

    defer_plotly_viewer()
    stop = threading.Event()
    node: Node | None = None
    if defer_signals:
        from rclpy.signals import SignalHandlerOptions

        rclpy.init(args=list(sys.argv if args is None else args), signal_handler_options=SignalHandlerOptions.NO)

        def on_signal(signum: int, frame: Any) -> None:
            if node is None:
                raise KeyboardInterrupt  # still being built: end as rclpy's handler would
            stop.set()

        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, on_signal)
    else:
        rclpy.init(args=list(sys.argv if args is None else args))
    # before the node: a SIGTERM while the node is built shuts the context down, and nothing
    # (no executor, no guard condition) can be created in it afterwards
    executor = MultiThreadedExecutor() if multi_threaded else SingleThreadedExecutor()
    try:
        # rclpy's handler (or the deferred one) is in place: a Ctrl-C held
        # during start-up (launcher) is taken here and ends the node as any Ctrl-C does
        accept_interrupts()
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
        spin_until_shutdown(executor, stop)
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except Exception:
        if rclpy.ok():
            raise
        # the context was shut down (SIGTERM) while the node was being built: its rclpy calls
        # fail because of that, a normal end
    finally:
        close_nodes(executor, [node] if node is not None else [])
    return EXIT_OK


def spin_until_shutdown(executor: Executor, stop: threading.Event | None = None) -> None:
    """Spin ``executor`` until its context is shut down (rclpy's SIGINT/SIGTERM handlers, an external shutdown)
    or ``stop`` is set, looking every `SIGNAL_POLL_S`.

    Not ``executor.spin()``: rclpy's signal handler wakes the executors (their signal guard condition) before
    it shuts the contexts down. A wait woken in between finds the context still up, and the next wait, with no
    timeout, is never woken: the process hangs after the signal (1 SIGTERM in 80 sent just after start).
    """
    try:
        while (stop is None or not stop.is_set()) and executor.context.ok():
            executor.spin_once(timeout_sec=SIGNAL_POLL_S)
    except ExternalShutdownException:
        pass  # the context went down during a wait: the end this waits for


def stop_executor(executor: Executor, grace_s: float = CALLBACK_GRACE_S) -> bool:
    """``executor`` takes no new work, and the callbacks its threads still run end (waited for at most
    ``grace_s``); True when none is left running.

    rclpy's own ``Executor.shutdown`` does not do it: it returns without waiting (rclpy 7.1 checks its
    shutdown flag after setting it), and a `MultiThreadedExecutor` never stops its thread pool, whose
    callbacks go on after the nodes they use are gone. So this waits for rclpy's count of running
    callbacks, then stops the pool (queued callbacks cancelled) and joins its threads.
    """
    import concurrent.futures

    deadline = time.monotonic() + grace_s
    executor.shutdown(timeout_sec=0.0)  # no new work; "don't wait" where rclpy would
    tracker = getattr(executor, "_work_tracker", None)
    done = bool(tracker.wait(grace_s)) if tracker is not None else True
    pool = getattr(executor, "_executor", None)
    if isinstance(pool, concurrent.futures.ThreadPoolExecutor):
        pool.shutdown(wait=False, cancel_futures=True)
        for thread in list(getattr(pool, "_threads", ())):
            thread.join(max(0.0, deadline - time.monotonic()))
            done = done and not thread.is_alive()
    return done


def close_nodes(executor: Executor, nodes: Sequence[Node], context: Any = None,
                grace_s: float = CALLBACK_GRACE_S) -> None:
    """The way out of a process's nodes (module doc): every node told (`LsuNode.begin_shutdown`: a running
    callback winds down), `stop_executor`, every node destroyed (each reaches its safe state in
    ``destroy_node``), then ``context`` (None: the default one) shut down."""
    try:
        for node in nodes:
            if isinstance(node, LsuNode):
                node.begin_shutdown()
        if not stop_executor(executor, grace_s):
            for node in nodes[:1]:
                node.get_logger().warning(f"a callback was still running {grace_s:g} s after the shutdown began; "
                                          "destroying the nodes anyway")
    finally:
        try:
            for node in nodes:
                node.destroy_node()
        finally:
            rclpy.try_shutdown(context=context)


def main_of(node_class: type[Node], *, multi_threaded: bool = False,
            startup_errors: tuple[type[BaseException], ...] = (), program: str = "", defer_signals: bool = False
            ) -> Callable[..., int]:
    """A console-script ``main(args=None)`` running ``node_class`` with `run_node`."""

    def main(args: list[str] | None = None) -> int:
        return run_node(node_class, args, multi_threaded=multi_threaded, startup_errors=startup_errors,
                        program=program, defer_signals=defer_signals)

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
