"""The GP32 units the driver's tests run against: the Python emulator and the real firmware in
the HC08 simulator (built once per session, one simulator per test module, power-cycled per test)."""

from __future__ import annotations

import pytest

from lsu_driver.emulator import EmulatorConfig, Faults, Gp32Emulator
from lsu_driver.firmware import FirmwareUnavailable, Gp32Firmware, build, toolchain_missing

START_POSITION = 20.0  # carriage position at power-on in every unit test [steps]


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Tests on the firmware run in `make test`'s serial part: a running simulator takes a core and
    the firmware's time follows it, and every such test builds the image in firmware/gp32/build
    (two workers running make there at once would race)."""
    for item in items:
        params = getattr(item, "callspec", None)
        if "firmware_build" in getattr(item, "fixturenames", ()) or (
                params is not None and params.params.get("unit") == "firmware"):
            item.add_marker(pytest.mark.serial)


@pytest.fixture(scope="session")
def firmware_build():
    """The firmware image, built with SDCC; skips (with the reason) where sdcc/ucsim are missing."""
    reason = toolchain_missing()
    if reason:
        pytest.skip(f"firmware tests need the GP32 toolchain: {reason}")
    try:
        return build()
    except FirmwareUnavailable as exc:
        pytest.fail(str(exc))


@pytest.fixture(scope="module")
def firmware_unit(firmware_build, tmp_path_factory):
    link = tmp_path_factory.mktemp("gp32fw") / "gp32"
    unit = Gp32Firmware(EmulatorConfig(start_position_steps=START_POSITION), Faults(seed=1), link=str(link),
                        image=firmware_build.sim_image).start()
    assert unit.wait_booted(), unit.log
    unit.power_off()  # each test powers it on (`unit`)
    yield unit
    unit.close()


@pytest.fixture(params=["emulator", "firmware"])
def unit(request, tmp_path):
    """A unit at START_POSITION, just powered on, not homed, behind ``unit.link``."""
    if request.param == "emulator":
        emu = Gp32Emulator(EmulatorConfig(start_position_steps=START_POSITION), Faults(seed=1),
                           link=str(tmp_path / "gp32"), control=str(tmp_path / "gp32.ctl")).start()
        yield emu
        emu.close()
    else:
        firmware = request.getfixturevalue("firmware_unit")
        firmware.clear_faults()
        firmware.reset(carriage_at=START_POSITION)
        yield firmware
        firmware.power_off()  # a running simulator takes a core: not while other tests run
