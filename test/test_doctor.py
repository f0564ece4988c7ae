"""`lsu doctor` passes on a good setup and names the reason when it is not."""


def test_doctor_passes_and_reports_the_environment(lsu_cli):
    result = lsu_cli("doctor", "--graph", timeout=60)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "LOCALHOST" in result.stdout and "rmw_fastrtps_cpp" in result.stdout
    assert "graph" in result.stdout and "all checks passed" in result.stdout


def test_doctor_fails_with_a_named_reason_when_interfaces_are_broken(lsu_cli, tmp_path):
    # a stale/half-built lsu_interfaces shadowing the real one, as after an interrupted build
    shadow = tmp_path / "lsu_interfaces"
    shadow.mkdir()
    (shadow / "__init__.py").write_text("raise ImportError('lsu_interfaces was not built')\n")
    result = lsu_cli("doctor", env={"PYTHONPATH": str(tmp_path)}, timeout=60)
    assert result.returncode != 0
    assert "FAIL  interfaces" in result.stdout and "make setup" in result.stdout
    assert "interfaces" in result.stderr


def test_doctor_warns_when_discovery_is_not_localhost(lsu_cli):
    result = lsu_cli("doctor", env={"ROS_AUTOMATIC_DISCOVERY_RANGE": "SUBNET"}, timeout=60)
    # not a failure (the user chose it), but said plainly; and lsu kept the user's choice
    assert "WARN  discovery" in result.stdout and "SUBNET (from your environment)" in result.stdout
