"""The power source's Modbus register map (docs/contract.md §5) as data, and pure encode/decode.

Two contiguous blocks of holding registers, exchanged in one read/write-multiple-registers
call (function 0x17) per 10 ms cycle: the host writes the command block 0xF000..0xF00D and
reads the status block 0xF100..0xF110 in the same transaction. Registers inside a block that
the map does not name are written as 0 and ignored on read.

No I/O here: the Modbus driver, the simulator and the CAN codec all use these tables.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from core.errors import CellError

# --- bits (shared by the Modbus map and the CAN frames) -----------------------------------

#: Command bits of 0xF001 (and of WELD_CMD on CAN), name -> bit number.
COMMAND_BITS: dict[str, int] = {
    "weld_start": 0,
    "robot_ready": 1,
    "error_reset": 2,    # acts on the rising edge
    "gas_test": 3,
    "wire_inch": 4,
    "wire_retract": 5,
}

#: Status bits of 0xF101 (and of WELD_STATUS on CAN), name -> bit number.
STATUS_BITS: dict[str, int] = {
    "heartbeat": 0,
    "ready": 1,
    "arc_stable": 2,
    "current_flow": 3,
    "main_current": 4,
    "collision_ok": 5,
    "gas_fault": 6,
    "wire_out": 7,
    "process_active": 12,
    "motion_release": 13,
    "wire_stick": 14,
}

MODES = {0: "synergic MIG", 1: "pulse", 2: "CMT-like"}
ARC_TRIM_LIMIT = 10.0      # arc-length trim, ± (0.1 steps)
DYNAMIC_TRIM_LIMIT = 5.0   # dynamic trim, ± (0.1 steps)


@dataclass(frozen=True)
class Register:
    """One mapped holding register."""

    name: str
    address: int
    kind: Literal["u16", "s16", "bits"]
    scale: float = 1.0          # engineering value = raw * scale
    direction: Literal["command", "status"] = "command"


@dataclass(frozen=True)
class RegisterMap:
    """The command block (written) and the status block (read) of the power source."""

    command_start: int
    command_count: int
    status_start: int
    status_count: int
    registers: tuple[Register, ...]

    def by_name(self, name: str) -> Register:
        for r in self.registers:
            if r.name == name:
                return r
        raise CellError(f"power-source register map: no register named '{name}'")

    def validate(self) -> "RegisterMap":
        """Check every entry lies in its block, once; a wrong entry is a clear CellError."""
        seen: dict[int, str] = {}
        for r in self.registers:
            lo, n = ((self.command_start, self.command_count) if r.direction == "command"
                     else (self.status_start, self.status_count))
            if not lo <= r.address < lo + n:
                raise CellError(
                    f"power-source register map: '{r.name}' at 0x{r.address:04X} is outside the "
                    f"{r.direction} block 0x{lo:04X}..0x{lo + n - 1:04X}; fix the map entry")
            if r.address in seen:
                raise CellError(
                    f"power-source register map: '{r.name}' and '{seen[r.address]}' share "
                    f"address 0x{r.address:04X}; fix the map entry")
            if not 0 <= r.address <= 0xFFFF:
                raise CellError(f"power-source register map: '{r.name}' address out of 0..0xFFFF")
            seen[r.address] = r.name
        for need in ("watchdog", "command_bits", "mode", "job", "wfs_command", "arc_trim",
                     "dynamic_trim", "watchdog_echo", "status_bits", "error_number",
                     "voltage", "current", "wfs_actual"):
            self.by_name(need)
        if not 1 <= self.command_count <= 0x79 or not 1 <= self.status_count <= 0x7D:
            raise CellError("power-source register map: block sizes exceed one Modbus 0x17 call")
        return self


#: docs/contract.md §5, to the letter.
POWER_MAP = RegisterMap(
    command_start=0xF000,
    command_count=0x0E,          # 0xF000..0xF00D
    status_start=0xF100,
    status_count=0x11,           # 0xF100..0xF110
    registers=(
        Register("watchdog", 0xF000, "u16"),
        Register("command_bits", 0xF001, "bits"),
        Register("mode", 0xF008, "u16"),
        Register("job", 0xF009, "u16"),
        Register("wfs_command", 0xF00B, "s16", 0.01),
        Register("arc_trim", 0xF00C, "s16", 0.1),
        Register("dynamic_trim", 0xF00D, "s16", 0.1),
        Register("watchdog_echo", 0xF100, "u16", direction="status"),
        Register("status_bits", 0xF101, "bits", direction="status"),
        Register("error_number", 0xF108, "u16", direction="status"),
        Register("voltage", 0xF10A, "u16", 0.01, direction="status"),
        Register("current", 0xF10B, "u16", 0.1, direction="status"),
        Register("wfs_actual", 0xF110, "s16", 0.01, direction="status"),
    ),
).validate()


# --- scaling ------------------------------------------------------------------------------

def to_raw(value: float, reg: Register) -> int:
    """Engineering value -> 16-bit register word (two's complement for s16)."""
    raw = int(round(value / reg.scale))
    if reg.kind == "s16":
        if not -0x8000 <= raw <= 0x7FFF:
            raise CellError(f"power source: {reg.name} {value} does not fit a signed 16-bit register")
        return raw & 0xFFFF
    if not 0 <= raw <= 0xFFFF:
        raise CellError(f"power source: {reg.name} {value} does not fit an unsigned 16-bit register")
    return raw


def from_raw(word: int, reg: Register) -> float:
    """16-bit register word -> engineering value."""
    word &= 0xFFFF
    if reg.kind == "s16" and word >= 0x8000:
        word -= 0x10000
    return word * reg.scale if reg.scale != 1.0 else float(word)


def pack_bits(flags: dict[str, bool], table: dict[str, int]) -> int:
    word = 0
    for name, on in flags.items():
        if on:
            word |= 1 << table[name]
    return word


def unpack_bits(word: int, table: dict[str, int]) -> dict[str, bool]:
    return {name: bool(word >> bit & 1) for name, bit in table.items()}


# --- blocks -------------------------------------------------------------------------------

def encode_command_block(values: dict[str, float], rmap: RegisterMap = POWER_MAP) -> list[int]:
    """Command values by register name (bits already packed) -> the words of the command block."""
    words = [0] * rmap.command_count
    for r in rmap.registers:
        if r.direction == "command" and r.name in values:
            words[r.address - rmap.command_start] = to_raw(values[r.name], r)
    return words


def decode_block(words: list[int], direction: str, rmap: RegisterMap = POWER_MAP) -> dict[str, float]:
    """The words of a block -> engineering values by register name."""
    start = rmap.command_start if direction == "command" else rmap.status_start
    out: dict[str, float] = {}
    for r in rmap.registers:
        if r.direction == direction:
            i = r.address - start
            if 0 <= i < len(words):
                out[r.name] = from_raw(words[i], r)
    return out
