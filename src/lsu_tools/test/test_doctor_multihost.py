"""`lsu doctor`'s multi-host checks on settings given as data (no traffic: routes are asked of the kernel)."""

from lsu_scan.rosenv import EnvReport
from lsu_tools.doctor import multi_host_checks


def by_name(checks):
    return {(c.name, c.status): c.detail for c in checks}


def test_localhost_without_peers_is_one_line_saying_dds_stays_here():
    checks = multi_host_checks({"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": "7"})
    assert [(c.status, c.name) for c in checks] == [("OK", "multi-host")]
    assert "stays on this machine" in checks[0].detail


def test_off_and_shared_memory_only_are_failures_that_say_what_to_set():
    checks = by_name(multi_host_checks({"ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF", "ROS_STATIC_PEERS": "127.0.0.1",
                                        "ROS_DOMAIN_ID": "7", "FASTDDS_BUILTIN_TRANSPORTS": "SHM"}))
    assert "use SUBNET" in checks[("multi-host discovery", "FAIL")]
    assert "UDPv4" in checks[("multi-host transport", "FAIL")]


def test_a_defaulted_domain_is_a_warning_and_a_peer_on_this_machine_is_named():
    report = EnvReport("SUBNET", False, "0", True)
    checks = by_name(multi_host_checks({"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET", "ROS_DOMAIN_ID": "0",
                                        "ROS_STATIC_PEERS": "127.0.0.1"}, report))
    assert "same ROS_DOMAIN_ID on both PCs" in checks[("multi-host domain", "WARN")]
    assert "this machine itself" in checks[("multi-host peer", "WARN")]
    assert "static peers 127.0.0.1" in checks[("multi-host discovery", "OK")]
