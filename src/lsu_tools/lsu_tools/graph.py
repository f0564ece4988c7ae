"""`lsu node|topic|service|param ...`: graph introspection on the rclpy graph API.

PyPI has no ros2cli; these commands give lab users the everyday part of it with the same
output shapes (`ros2 topic echo` YAML with `---` separators, `ros2 param dump` YAML).
"""

from __future__ import annotations

import argparse
import math
import re
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any

import yaml

from lsu_bags.rosmsg import InterfaceError, fill, get_interface, parse_yaml_mapping, to_data, to_yaml, type_name_of

_TYPE_RE = re.compile(r"^[A-Za-z_]\w*/(?:(?:msg|srv|action)/)?[A-Z]\w*$")


# Fast DDS on localhost: a running graph is discovered within ~1-3 s, in bursts; a second without
# anything new means it is complete (a lost announcement is repeated within that time too).
DISCOVERY_QUIET_S = 1.5
DISCOVERY_MIN_S = 1.0
DISCOVERY_MAX_S = 10.0
# how long a quiet graph still waits for the names of endpoints whose node is unknown: a name on its way comes
# within seconds; one that never comes is a leftover (a process that ended without leaving the graph, a DDS
# participant that is no ROS node), which must not hold every listing to its maximum
NAME_WAIT_S = 4 * DISCOVERY_QUIET_S
UNKNOWN_NODE = "_NODE_NAME_UNKNOWN_"  # rmw's name for the node of an endpoint whose node info has not come


class GraphError(RuntimeError):
    """A graph command cannot complete (no such node/topic/service, timeout); one line for the user."""


class GraphClient:
    """A hidden node in its own context, for one CLI command."""

    def __init__(self) -> None:
        import os

        import rclpy
        from rclpy.context import Context
        from rclpy.executors import SingleThreadedExecutor

        self.rclpy = rclpy
        self.context = Context()
        rclpy.init(context=self.context)
        # a leading underscore hides the node from `lsu node list`, like ros2cli's own nodes
        self.node = rclpy.create_node(f"_lsu_cli_{os.getpid()}", context=self.context,
                                      start_parameter_services=False)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.unnamed: list[str] = []  # endpoints whose node never named itself in the last `wait_for_discovery`
        self.executor.add_node(self.node)

    def __enter__(self) -> GraphClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.executor.shutdown(timeout_sec=1.0)
        self.node.destroy_node()
        self.rclpy.try_shutdown(context=self.context)

    def spin_for(self, seconds: float) -> None:
        """Process callbacks for ``seconds``."""
        end = time.monotonic() + seconds
        while time.monotonic() < end and self.context.ok():
            self.executor.spin_once(timeout_sec=min(0.05, max(0.0, end - time.monotonic())))

    def spin_until(self, done: Callable[[], bool], timeout_s: float) -> bool:
        """Process callbacks until ``done()`` or the timeout; returns ``done()``."""
        end = time.monotonic() + timeout_s
        while not done():
            if time.monotonic() >= end or not self.context.ok():
                return done()
            self.executor.spin_once(timeout_sec=0.05)
        return True

    def graph_snapshot(self) -> tuple[Any, ...]:
        """Every node, topic, service and endpoint count this node sees now (hashable)."""
        n = self.node
        topics = tuple(sorted((name, tuple(types)) for name, types in n.get_topic_names_and_types()))
        counts = tuple((name, n.count_publishers(name), n.count_subscribers(name)) for name, _ in topics)
        return (tuple(sorted(n.get_node_names_and_namespaces())), topics, counts,
                tuple(sorted((name, tuple(types)) for name, types in n.get_service_names_and_types())))

    def endpoints_without_node(self) -> list[str]:
        """Publishers and subscriptions seen whose node is not known yet, each as
        ``"publisher on /topic [type] (pid N: command)"``.

        An endpoint comes with DDS discovery, its node's name with the node's ros_discovery_info sample,
        which arrives separately and, on a loaded host, seconds later: until then the node is running
        but missing from every listing. One that stays is a process's leftover endpoint: the pid says whose.
        """
        n, missing = self.node, []
        for topic, _ in n.get_topic_names_and_types():
            for kind, infos in (("publisher", n.get_publishers_info_by_topic(topic)),
                                ("subscription", n.get_subscriptions_info_by_topic(topic))):
                missing += [f"{kind} on {topic} [{i.topic_type}]{_owner(i.endpoint_gid)}"
                            for i in infos if i.node_name == UNKNOWN_NODE]
        return missing

    def wait_for_discovery(self, max_s: float, quiet_s: float = DISCOVERY_QUIET_S,
                           min_s: float = DISCOVERY_MIN_S, name_wait_s: float = NAME_WAIT_S) -> float:
        """Listen until no node, topic, service or endpoint appeared for ``quiet_s`` (at least ``min_s``,
        at most ``max_s`` seconds); returns the seconds listened.

        There is no daemon keeping the graph: each command discovers it afresh, and how long that
        takes depends on how many nodes there are and how busy the host is, so a fixed wait is
        either too short (entities missed) or too long. Quiet does not count while an endpoint's node
        is unknown (`endpoints_without_node`): its name is still on the way, for up to ``name_wait_s``; those
        still unnamed then (or at ``max_s``) are left in ``unnamed``.
        """
        start = time.monotonic()
        last_change, seen = start, self.graph_snapshot()
        me = (self.node.get_name(), self.node.get_namespace())
        naming_since: float | None = None  # when quiet was first put off for a name on its way
        self.unnamed = []
        while self.context.ok():
            now = time.monotonic()
            # quiet only counts once another participant is seen: on a busy host the first
            # announcement can take seconds, and "nothing new" before it means nothing yet
            others = any((name, ns) != me for name, ns in seen[0])
            if now - start >= max_s:
                self.unnamed = self.endpoints_without_node()
                break
            if others and now - start >= min_s and now - last_change >= quiet_s:
                unnamed = self.endpoints_without_node()
                if not unnamed:
                    break
                naming_since = now if naming_since is None else naming_since
                if now - naming_since >= name_wait_s:
                    self.unnamed = unnamed  # leftovers, not names on the way (`NAME_WAIT_S`)
                    break
                last_change = now  # a node's name is on the way: it is news still to come
            self.executor.spin_once(timeout_sec=0.05)
            current = self.graph_snapshot()
            if current != seen:
                seen, last_change = current, time.monotonic()
        return time.monotonic() - start

    def wait_for_type(self, name: str, lister: Callable[[], list[tuple[str, list[str]]]],
                      timeout_s: float, what: str) -> str:
        found: dict[str, list[str]] = {}

        def seen() -> bool:
            found.update(dict(lister()))
            return name in found

        if not self.spin_until(seen, timeout_s):
            raise GraphError(f"{what} '{name}' not found on the graph within {timeout_s:g} s; "
                             f"is the node running in ROS_DOMAIN_ID={_domain()}? "
                             f"(`lsu {what} list` shows what is there)")
        types = found[name]
        if len(types) != 1:
            raise GraphError(f"{what} '{name}' has several types ({', '.join(types)}); give the type explicitly")
        return types[0]


def _owner(gid: Sequence[int]) -> str:
    """`` (pid N: command)`` of the local process that owns a Fast DDS endpoint, else ``""``.

    Fast DDS writes the low 16 bits of the owner's process id into bytes 4-5 of every GUID (after the
    vendor id 1.15 and two bytes of host id): the first running pid with those low bits is taken.
    """
    import os
    from pathlib import Path

    if len(gid) < 6 or list(gid[:2]) != [1, 15]:
        return ""
    low = gid[4] | gid[5] << 8
    for pid in range(low, 1 << 22, 1 << 16):
        try:
            command = Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        return f" (pid {pid}{' (this process)' if pid == os.getpid() else ''}: {command.strip()[:160]})"
    return f" (pid {low} or another with those low 16 bits, not running here)"


def _domain() -> str:
    import os

    return os.environ.get("ROS_DOMAIN_ID", "0")


def _abs(name: str) -> str:
    return name if name.startswith("/") else "/" + name


def _print(text: str) -> None:
    sys.stdout.write(text)
    sys.stdout.flush()


# ----------------------------------------------------------------------------------- nodes
def cmd_node_list(args: argparse.Namespace) -> int:
    with GraphClient() as g:
        g.wait_for_discovery(args.wait)
        names = sorted({(ns.rstrip("/") + "/" + n) for n, ns in g.node.get_node_names_and_namespaces()
                        if not n.startswith("_")})
        if g.unnamed:
            sys.stderr.write(f"note: {len(g.unnamed)} endpoint(s) on this domain belong to no named node (a process "
                             "that ended without leaving the graph, or a DDS participant that is no ROS node): "
                             + "; ".join(g.unnamed[:5]) + "\n")
    for name in names:
        print(name)
    return 0


def cmd_node_info(args: argparse.Namespace) -> int:
    target = _abs(args.node)
    ns, _, name = target.rpartition("/")
    ns = ns or "/"
    with GraphClient() as g:
        g.wait_for_discovery(args.wait)
        if (name, ns) not in g.node.get_node_names_and_namespaces():
            raise GraphError(f"node '{target}' not found (see `lsu node list`)")
        sections = [
            ("Subscribers", g.node.get_subscriber_names_and_types_by_node(name, ns)),
            ("Publishers", g.node.get_publisher_names_and_types_by_node(name, ns)),
            ("Service Servers", g.node.get_service_names_and_types_by_node(name, ns)),
        ]
    print(target)
    for title, items in sections:
        print(f"  {title}:")
        for topic, types in sorted(items):
            print(f"    {topic}: {', '.join(types)}")
    return 0


# ---------------------------------------------------------------------------------- topics
def cmd_topic_list(args: argparse.Namespace) -> int:
    with GraphClient() as g:
        g.wait_for_discovery(args.wait)
        topics = sorted(g.node.get_topic_names_and_types())
    for name, types in topics:
        print(f"{name} [{', '.join(types)}]" if args.show_types else name)
    return 0


def cmd_topic_info(args: argparse.Namespace) -> int:
    topic = _abs(args.topic)
    with GraphClient() as g:
        type_name = g.wait_for_type(topic, g.node.get_topic_names_and_types, args.timeout, "topic")
        pubs = g.node.get_publishers_info_by_topic(topic)
        subs = g.node.get_subscriptions_info_by_topic(topic)
    print(f"Type: {type_name}")
    print(f"Publisher count: {len(pubs)}")
    for info in pubs:
        print(f"  {info.node_namespace.rstrip('/')}/{info.node_name}: {_qos_text(info.qos_profile)}")
    print(f"Subscription count: {len(subs)}")
    for info in subs:
        print(f"  {info.node_namespace.rstrip('/')}/{info.node_name}: {_qos_text(info.qos_profile)}")
    return 0


def _qos_text(qos: Any) -> str:
    return f"{qos.reliability.name.lower()}, {qos.durability.name.lower()}"


def _subscription_qos(g: GraphClient, topic: str) -> Any:
    """QoS that receives from every current publisher, and latched data when all latch."""
    from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy

    qos = QoSProfile(depth=10)
    pubs = g.node.get_publishers_info_by_topic(topic)
    if pubs and all(p.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL for p in pubs):
        qos.durability = DurabilityPolicy.TRANSIENT_LOCAL
    if any(p.qos_profile.reliability == ReliabilityPolicy.BEST_EFFORT for p in pubs):
        qos.reliability = ReliabilityPolicy.BEST_EFFORT
    return qos


def cmd_topic_echo(args: argparse.Namespace) -> int:
    topic = _abs(args.topic)
    count = 1 if args.once else args.count
    limit = None if args.full else args.array_limit
    with GraphClient() as g:
        type_name = args.type or g.wait_for_type(topic, g.node.get_topic_names_and_types, args.timeout, "topic")
        msg_cls = get_interface(type_name, "msg")
        if args.type:
            g.spin_for(0.3)  # let publishers be discovered so the QoS can match them
        received = [0]

        def on_msg(msg: Any) -> None:
            if count and received[0] >= count:
                return
            received[0] += 1
            _print(to_yaml(msg, limit) + "---\n")

        g.node.create_subscription(msg_cls, topic, on_msg, _subscription_qos(g, topic))
        deadline = args.timeout if count else math.inf
        got = g.spin_until(lambda: bool(count) and received[0] >= count, deadline)
        if count and not got:
            raise GraphError(f"received {received[0]} of {count} message(s) on '{topic}' within "
                             f"{args.timeout:g} s")
    return 0


def cmd_topic_hz(args: argparse.Namespace) -> int:
    topic = _abs(args.topic)
    with GraphClient() as g:
        type_name = g.wait_for_type(topic, g.node.get_topic_names_and_types, args.timeout, "topic")
        stamps: list[float] = []
        g.node.create_subscription(get_interface(type_name, "msg"), topic,
                                   lambda _m: stamps.append(time.monotonic()), _subscription_qos(g, topic))
        end = time.monotonic() + args.duration if args.duration else math.inf
        next_report = time.monotonic() + 1.0
        while time.monotonic() < end and g.context.ok():
            g.spin_for(min(0.1, max(0.0, end - time.monotonic())))
            if time.monotonic() >= next_report:
                next_report += 1.0
                print(_rate_report(stamps[-args.window:]) if len(stamps) > 1 else "no new messages")
                sys.stdout.flush()
        if len(stamps) < 2:
            raise GraphError(f"fewer than 2 messages on '{topic}'; cannot measure a rate")
    return 0


def _rate_report(stamps: Sequence[float]) -> str:
    gaps = [b - a for a, b in zip(stamps, stamps[1:])]
    mean = statistics.fmean(gaps)
    std = statistics.pstdev(gaps) if len(gaps) > 1 else 0.0
    return (f"average rate: {1.0 / mean:.3f}\n\tmin: {min(gaps):.3f}s max: {max(gaps):.3f}s "
            f"std dev: {std:.5f}s window: {len(stamps)}")


def cmd_topic_pub(args: argparse.Namespace) -> int:
    topic = _abs(args.topic)
    msg_cls = get_interface(args.type, "msg")
    msg = fill(msg_cls(), parse_yaml_mapping(args.values))
    times = 1 if args.once else args.times
    with GraphClient() as g:
        pub = g.node.create_publisher(msg_cls, topic, 10)
        g.spin_until(lambda: pub.get_subscription_count() > 0, args.wait_matching)
        sent = 0
        while g.context.ok() and (not times or sent < times):
            pub.publish(msg)
            sent += 1
            print(f"publishing #{sent}: {to_data(msg, 8)}")
            g.spin_for(1.0 / args.rate if (not times or sent < times) else 0.2)
    return 0


# -------------------------------------------------------------------------------- services
def cmd_service_list(args: argparse.Namespace) -> int:
    with GraphClient() as g:
        g.wait_for_discovery(args.wait)
        services = sorted(g.node.get_service_names_and_types())
    for name, types in services:
        if not args.all and name.rsplit("/", 1)[-1] in _PARAM_SERVICES:
            continue
        print(f"{name} [{', '.join(types)}]" if args.show_types else name)
    return 0


_PARAM_SERVICES = {"describe_parameters", "get_parameter_types", "get_parameters", "list_parameters",
                   "set_parameters", "set_parameters_atomically", "get_type_description"}


def cmd_service_call(args: argparse.Namespace) -> int:
    service = _abs(args.service)
    positional = list(args.rest)
    if len(positional) > 2:
        raise GraphError("usage: lsu service call SERVICE [TYPE] [VALUES]")
    type_name = positional.pop(0) if positional and _TYPE_RE.match(positional[0]) else None
    values = positional[0] if positional else ""
    with GraphClient() as g:
        if type_name is None:
            type_name = g.wait_for_type(service, g.node.get_service_names_and_types, args.timeout, "service")
        srv_cls = get_interface(type_name, "srv")
        request = fill(srv_cls.Request(), parse_yaml_mapping(values))
        client = g.node.create_client(srv_cls, service)
        if not g.spin_until(client.service_is_ready, args.timeout):
            raise GraphError(f"service '{service}' is not available within {args.timeout:g} s "
                             f"(`lsu service list` shows what is there)")
        print(f"requester: making request: {type_name_of(srv_cls)}.Request({to_data(request, 8)})")
        future = client.call_async(request)
        if not g.spin_until(future.done, args.timeout):
            raise GraphError(f"no response from '{service}' within {args.timeout:g} s")
        print("response:")
        _print(to_yaml(future.result(), None if args.full else 16))
    return 0


# ------------------------------------------------------------------------------ parameters
def _param_call(g: GraphClient, node: str, service: str, request: Any, timeout_s: float) -> Any:
    from rcl_interfaces import srv

    srv_cls = {"list_parameters": srv.ListParameters, "get_parameters": srv.GetParameters,
               "set_parameters": srv.SetParameters, "describe_parameters": srv.DescribeParameters}[service]
    client = g.node.create_client(srv_cls, f"{_abs(node)}/{service}")
    if not g.spin_until(client.service_is_ready, timeout_s):
        raise GraphError(f"node '{_abs(node)}' not found or has no parameter services "
                         f"(`lsu node list` shows the running nodes)")
    future = client.call_async(request)
    if not g.spin_until(future.done, timeout_s):
        raise GraphError(f"node '{_abs(node)}' did not answer {service} within {timeout_s:g} s")
    return future.result()


def _value_to_python(value: Any) -> Any:
    from rclpy.parameter import parameter_value_to_python

    result = parameter_value_to_python(value)
    # array.array and ndarray are iterable; mypy cannot tell from the tuple built at run time
    return list(result) if isinstance(result, (tuple, array_types())) else result  # type: ignore[call-overload]


def array_types() -> tuple[type, ...]:
    import array

    import numpy as np

    return (array.array, np.ndarray)


def _get(g: GraphClient, node: str, names: list[str], timeout_s: float) -> dict[str, Any]:
    from rcl_interfaces.msg import ParameterType
    from rcl_interfaces.srv import GetParameters

    result = _param_call(g, node, "get_parameters", GetParameters.Request(names=names), timeout_s)
    values = list(result.values)
    if len(values) != len(names):  # rclpy answers an unknown name with an empty list
        values = [None] * len(names)
    out: dict[str, Any] = {}
    for name, value in zip(names, values):
        if value is None or value.type == ParameterType.PARAMETER_NOT_SET:
            raise GraphError(f"node '{_abs(node)}' has no parameter '{name}' (`lsu param list {node}`)")
        out[name] = _value_to_python(value)
    return out


def _list(g: GraphClient, node: str, timeout_s: float) -> list[str]:
    from rcl_interfaces.srv import ListParameters

    return sorted(_param_call(g, node, "list_parameters", ListParameters.Request(), timeout_s).result.names)


def cmd_param_list(args: argparse.Namespace) -> int:
    with GraphClient() as g:
        for name in _list(g, args.node, args.timeout):
            print(f"  {name}")
    return 0


def cmd_param_get(args: argparse.Namespace) -> int:
    with GraphClient() as g:
        value = _get(g, args.node, [args.name], args.timeout)[args.name]
    print(yaml.safe_dump(value, default_flow_style=True).strip().removesuffix("\n...").removesuffix("..."))
    return 0


def cmd_param_set(args: argparse.Namespace) -> int:
    from rcl_interfaces.srv import SetParameters
    from rclpy.parameter import Parameter

    try:
        value = yaml.safe_load(args.value)
    except yaml.YAMLError:
        value = args.value
    with GraphClient() as g:
        current = _get(g, args.node, [args.name], args.timeout)[args.name]
        if isinstance(current, float) and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)  # `set rate 5` on a float parameter means 5.0
        request = SetParameters.Request(parameters=[Parameter(args.name, value=value).to_parameter_msg()])
        result = _param_call(g, args.node, "set_parameters", request, args.timeout).results[0]
    if not result.successful:
        raise GraphError(f"setting '{args.name}' failed: {result.reason or 'rejected by the node'}")
    print("Set parameter successful")
    return 0


def cmd_param_dump(args: argparse.Namespace) -> int:
    from rcl_interfaces.srv import DescribeParameters

    node = _abs(args.node)
    with GraphClient() as g:
        names = _list(g, node, args.timeout)
        values = _get(g, node, names, args.timeout) if names else {}
        described = _param_call(g, node, "describe_parameters", DescribeParameters.Request(names=names),
                                args.timeout).descriptors
    params: dict[str, Any] = {}
    for name in names:
        cursor = params
        *parents, leaf = name.split(".")
        for part in parents:
            cursor = cursor.setdefault(part, {})
        cursor[leaf] = values[name]
    lines = [f"{node}:", "  ros__parameters:"]
    body = yaml.safe_dump(params, sort_keys=True, default_flow_style=False, width=100).splitlines()
    notes = {d.name.split(".")[-1]: d.description for d in described if d.description}
    for line in body:
        key = line.strip().split(":", 1)[0]
        is_leaf = not line.rstrip().endswith(":")
        note = notes.get(key) if is_leaf else None
        lines.append("    " + line + (f"  # {note}" if note else ""))
    text = "\n".join(lines) + "\n"
    if args.output:
        with open(args.output, "w") as handle:
            handle.write(text)
        print(f"wrote {args.output}")
    else:
        _print(text)
    return 0


# ---------------------------------------------------------------------------- registration
def register(sub: argparse._SubParsersAction[argparse.ArgumentParser]) -> None:
    """Add `node`, `topic`, `service` and `param` to the `lsu` parser."""
    def wait_opt(p: argparse.ArgumentParser, default: float = DISCOVERY_MAX_S) -> None:
        p.add_argument("--wait", type=float, default=default, metavar="S",
                       help=f"listen for discovery until nothing new appeared for {DISCOVERY_QUIET_S:g} s, at most "
                            f"S seconds (default {default:g})")

    def timeout_opt(p: argparse.ArgumentParser, default: float = 5.0) -> None:
        p.add_argument("--timeout", type=float, default=default, metavar="S",
                       help=f"give up after this many seconds (default {default})")

    node = sub.add_parser("node", help="nodes on the graph").add_subparsers(dest="verb", required=True)
    p = node.add_parser("list", help="list running nodes")
    wait_opt(p)
    p.set_defaults(func=cmd_node_list)
    p = node.add_parser("info", help="topics and services of a node")
    p.add_argument("node")
    wait_opt(p)
    p.set_defaults(func=cmd_node_info)

    topic = sub.add_parser("topic", help="topics: list, info, echo, hz, pub").add_subparsers(dest="verb", required=True)
    p = topic.add_parser("list", help="list topics")
    p.add_argument("-t", "--show-types", action="store_true", help="also print each topic's type")
    wait_opt(p)
    p.set_defaults(func=cmd_topic_list)
    p = topic.add_parser("info", help="type, publishers and subscribers of a topic")
    p.add_argument("topic")
    timeout_opt(p)
    p.set_defaults(func=cmd_topic_info)
    p = topic.add_parser("echo", help="print messages as YAML")
    p.add_argument("topic")
    p.add_argument("type", nargs="?", help="message type (default: taken from the graph)")
    p.add_argument("--once", action="store_true", help="print one message and exit")
    p.add_argument("--count", type=int, default=0, help="exit after this many messages (0 = run until Ctrl-C)")
    p.add_argument("--full", action="store_true", help="print long arrays whole")
    p.add_argument("--array-limit", type=int, default=16, help="array items shown before '... N more'")
    timeout_opt(p)
    p.set_defaults(func=cmd_topic_echo)
    p = topic.add_parser("hz", help="measure the publish rate")
    p.add_argument("topic")
    p.add_argument("--window", type=int, default=100, help="messages in the rate window")
    p.add_argument("--duration", type=float, default=0.0, help="stop after S seconds (0 = until Ctrl-C)")
    timeout_opt(p)
    p.set_defaults(func=cmd_topic_hz)
    p = topic.add_parser("pub", help="publish a message")
    p.add_argument("topic")
    p.add_argument("type", help="message type, e.g. std_msgs/msg/String")
    p.add_argument("values", nargs="?", default="", help="YAML mapping of fields, e.g. \"{data: hi}\"")
    p.add_argument("--once", action="store_true", help="publish one message and exit")
    p.add_argument("--times", type=int, default=0, help="publish this many messages (0 = until Ctrl-C)")
    p.add_argument("-r", "--rate", type=float, default=1.0, help="messages per second (default 1)")
    p.add_argument("--wait-matching", type=float, default=2.0, metavar="S",
                   help="wait up to S seconds for a subscriber before the first message")
    p.set_defaults(func=cmd_topic_pub)

    service = sub.add_parser("service", help="services: list, call").add_subparsers(dest="verb", required=True)
    p = service.add_parser("list", help="list services")
    p.add_argument("-t", "--show-types", action="store_true", help="also print each service's type")
    p.add_argument("-a", "--all", action="store_true", help="include the nodes' parameter services")
    wait_opt(p)
    p.set_defaults(func=cmd_service_list)
    p = service.add_parser("call", help="call a service: lsu service call NAME [TYPE] [VALUES]")
    p.add_argument("service")
    p.add_argument("rest", nargs="*", metavar="TYPE/VALUES",
                   help="optional type (default: from the graph) and YAML request fields")
    p.add_argument("--full", action="store_true", help="print long arrays whole")
    timeout_opt(p, 10.0)
    p.set_defaults(func=cmd_service_call)

    param = sub.add_parser("param", help="node parameters: list, get, set, dump").add_subparsers(
        dest="verb", required=True)
    p = param.add_parser("list", help="parameter names of a node")
    p.add_argument("node")
    timeout_opt(p)
    p.set_defaults(func=cmd_param_list)
    p = param.add_parser("get", help="one parameter's value")
    p.add_argument("node")
    p.add_argument("name")
    timeout_opt(p)
    p.set_defaults(func=cmd_param_get)
    p = param.add_parser("set", help="set a parameter (value parsed as YAML)")
    p.add_argument("node")
    p.add_argument("name")
    p.add_argument("value")
    timeout_opt(p)
    p.set_defaults(func=cmd_param_set)
    p = param.add_parser("dump", help="all parameters as a ros__parameters YAML file, with descriptions")
    p.add_argument("node")
    p.add_argument("-o", "--output", help="write to this file instead of the screen")
    timeout_opt(p)
    p.set_defaults(func=cmd_param_dump)


__all__ = ["GraphError", "register", "InterfaceError"]
