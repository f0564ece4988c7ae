"""DDS isolation: localhost discovery and per-run domains."""

from lsu_scan import rosenv


def test_defaults_fill_only_what_the_user_left_unset():
    env = {"HOME": "/root"}
    report = rosenv.apply_defaults(env)
    assert env[rosenv.DISCOVERY_VAR] == "LOCALHOST" and report.discovery_set_by_lsu
    assert env[rosenv.DOMAIN_VAR] == "0" and report.domain_set_by_lsu
    env = {"HOME": "/root", rosenv.DISCOVERY_VAR: "SUBNET", rosenv.DOMAIN_VAR: "7"}
    report = rosenv.apply_defaults(env)
    assert env[rosenv.DISCOVERY_VAR] == "SUBNET" and not report.discovery_set_by_lsu
    assert env[rosenv.DOMAIN_VAR] == "7" and not report.domain_set_by_lsu


def test_frame_sized_malloc_settings_are_set_unless_the_user_chose_them():
    env = {"HOME": "/root", "MALLOC_TRIM_THRESHOLD_": "1000"}
    rosenv.apply_defaults(env)
    assert env["MALLOC_MMAP_THRESHOLD_"] == str(16 << 20)  # above a 640x480 bgr8 frame (921,600 bytes)
    assert int(env["MALLOC_MMAP_THRESHOLD_"]) > 640 * 480 * 3
    assert env["MALLOC_TRIM_THRESHOLD_"] == "1000"


def test_empty_environment_gets_a_home_for_ros_logging():
    env: dict = {}
    rosenv.apply_defaults(env)
    assert env["HOME"]


def test_two_claims_never_share_a_domain_and_release_frees_it():
    first = rosenv.claim_domain(start_hint=5)
    second = rosenv.claim_domain(start_hint=5)
    try:
        assert first.domain_id != second.domain_id
        freed = first.domain_id
        first.release()
        third = rosenv.claim_domain(start_hint=freed - 1)
        assert third.domain_id == freed
        third.release()
    finally:
        first.release()
        second.release()


def test_test_session_is_isolated():
    import os

    assert os.environ[rosenv.DISCOVERY_VAR] == "LOCALHOST"
    assert int(os.environ[rosenv.DOMAIN_VAR]) in rosenv.CLAIMABLE_DOMAINS
