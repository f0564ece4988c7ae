"""Graph listing waits for discovery to settle, not for a fixed time."""

from __future__ import annotations

import threading

from lsu_bringup.graph import DISCOVERY_QUIET_S, GraphClient


def test_listing_waits_while_nodes_keep_appearing(ros_context):
    import rclpy

    # nodes that come up one by one, each well within the quiet period of the one before, for
    # longer than the old fixed 3 s wait: every one of them must be listed
    gap_s = DISCOVERY_QUIET_S / 3
    count = int(3.0 / gap_s) + 3
    names = [f"late_node_{i}" for i in range(count)]
    # the first node makes the process's DDS participant (slow on a busy host); the others then
    # only add entities to the graph, like nodes of a launch coming up one by one
    created = [rclpy.create_node(names[0], namespace="/graphtest", context=ros_context)]
    stop = threading.Event()

    def bring_up() -> None:
        for name in names[1:]:
            if stop.wait(gap_s):
                return
            created.append(rclpy.create_node(name, namespace="/graphtest", context=ros_context))

    with GraphClient() as g:
        worker = threading.Thread(target=bring_up)
        worker.start()
        try:
            g.wait_for_discovery(max_s=60.0)
            seen = {n for n, ns in g.node.get_node_names_and_namespaces() if ns == "/graphtest"}
            finished_first = len(created) == count
        finally:
            stop.set()
            worker.join()
            for node in created:
                node.destroy_node()
    assert finished_first  # the wait outlasted the last node's start ...
    assert seen == set(names)  # ... and saw all of them


def test_listing_does_not_stop_before_the_first_other_participant_is_seen(ros_context):
    import rclpy

    # on a busy host the first announcement of the graph's nodes can come after the quiet period:
    # "nothing new for 1.5 s" before anything else was seen means nothing seen yet, not a settled graph
    late = {}

    def bring_up() -> None:
        late["node"] = rclpy.create_node("first_and_late", namespace="/graphtest2", context=ros_context)

    timer = threading.Timer(2 * (DISCOVERY_QUIET_S + 1.0), bring_up)
    with GraphClient() as g:
        timer.start()
        try:
            g.wait_for_discovery(max_s=60.0)
            seen = {n for n, ns in g.node.get_node_names_and_namespaces() if ns == "/graphtest2"}
        finally:
            timer.cancel()
            timer.join()
            if "node" in late:
                late["node"].destroy_node()
    assert seen == {"first_and_late"}
