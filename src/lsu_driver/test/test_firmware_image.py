"""The firmware image: it fits the MC68HC908GP32 and its vectors point into its code.

Ground truth: the GP32 data sheet's memory map (flash 0x8000-0xfdff, RAM 0x40-0x23f, vectors at
0xffdc-0xffff) checked against the Intel HEX records themselves, not the linker's own summary."""

from __future__ import annotations

FLASH = (0x8000, 0xFE00)
VECTORS = {0xFFFE: "reset", 0xFFF2: "TIM1 overflow", 0xFFE4: "SCI receive", 0xFFE2: "SCI transmit"}


def read_hex(path) -> dict[int, int]:
    """Address -> byte of an Intel HEX file (data records only; checksums verified)."""
    memory: dict[int, int] = {}
    for line in path.read_text().split():
        raw = bytes.fromhex(line[1:])
        assert sum(raw) & 0xFF == 0, f"bad checksum in {line}"
        count, address, kind = raw[0], raw[1] << 8 | raw[2], raw[3]
        if kind == 0:
            for i, value in enumerate(raw[4:4 + count]):
                memory[address + i] = value
    return memory


def test_the_image_fits_the_gp32_and_every_vector_points_into_flash(firmware_build):
    memory = read_hex(firmware_build.hex)
    code = [a for a in memory if a < 0xFF00]
    assert code and all(FLASH[0] <= a < FLASH[1] for a in code), "code outside the GP32's user flash"
    assert len(code) == firmware_build.size.flash_bytes - 2 * len(VECTORS)
    for address, name in VECTORS.items():
        target = memory[address] << 8 | memory[address + 1]
        assert FLASH[0] <= target < max(code), f"{name} vector 0x{target:04x}"
    assert memory[0xFFFE] << 8 | memory[0xFFFF] == 0x8000  # reset starts the C start-up at the start of flash
    # RAM: variables from 0x40 and at least 64 bytes of stack below 0x23f
    assert firmware_build.size.ram_end <= 0x240 - 64 and firmware_build.size.ram_bytes <= 512 - 64


def test_the_s19_image_holds_the_same_bytes_as_the_hex(firmware_build):
    memory = read_hex(firmware_build.hex)
    s19: dict[int, int] = {}
    for line in firmware_build.s19.read_text().split():
        if line.startswith("S1"):
            raw = bytes.fromhex(line[2:])
            assert (sum(raw) + 1) & 0xFF == 0, f"bad checksum in {line}"
            address = raw[1] << 8 | raw[2]
            for i, value in enumerate(raw[3:-1]):
                s19[address + i] = value
    assert s19 == memory
