"""`lsu gp32 send` against the emulator: replies and events told apart, errors counted."""

from lsu_driver.emulator import EmulatorConfig, Gp32Emulator


def test_send_prints_replies_and_events(tmp_path, lsu_cli):
    with Gp32Emulator(EmulatorConfig(start_position_steps=50.0), link=str(tmp_path / "gp32")) as emu:
        result = lsu_cli("gp32", "send", str(emu.link), "?", "P", "M+5", "--wait", timeout=60)
        assert result.returncode == 0, result.stdout + result.stderr
        out = result.stdout
        assert "< OK LSU-GP32 v2 track=470 speed=200" in out and "(reply)" in out
        assert "!DONE 5" in out and "(event)" in out
        assert emu.truth().counter_steps == 5
        refused = lsu_cli("gp32", "send", str(emu.link), "G100", timeout=60)
        assert refused.returncode == 1 and "ERR 3 not homed" in refused.stdout


def test_send_to_a_missing_port_is_one_line(tmp_path, lsu_cli):
    result = lsu_cli("gp32", "send", str(tmp_path / "none"), "?", timeout=60)
    assert result.returncode == 2 and "Traceback" not in result.stderr
    assert "lsu gp32 emulate" in result.stderr and len(result.stderr.strip().splitlines()) == 1


def test_firmware_build_names_the_images_and_their_size(firmware_build, lsu_cli):
    result = lsu_cli("gp32", "firmware", "build", timeout=300)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "lsu-gp32.s19" in result.stdout and "lsu-gp32-sim.ihx" in result.stdout
    assert f"{firmware_build.size.flash_bytes} B flash of 32768" in result.stdout
