"""The cell I/O coupler's Modbus map (docs/contract.md §5), one definition for the driver and the simulator.

Discrete inputs 0..3 and coils 0..4 in the order of INPUTS and COILS; input registers 0..1 in
the order of INPUT_REGISTERS, each the value times REGISTER_SCALE (0.1 °C, 0.1 L/min). The
driver reads every signal by its name here (drivers/cellio.decode_inputs), never by a position
of its own: this tuple alone says which input is the door and which the E-stop.
"""
from __future__ import annotations

DEVICE_ID = 1
INPUTS: tuple[str, ...] = ("door_closed", "estop_released", "gas_ok", "fume_ok")
COILS: tuple[str, ...] = ("gas_valve", "beacon_green", "beacon_amber", "beacon_red", "door_lock")
INPUT_REGISTERS: tuple[str, ...] = ("part_temperature_c", "gas_flow_l_min")
REGISTER_SCALE = 10.0
BEACON_COLOURS: tuple[str, ...] = ("green", "amber", "red")


def to_register(value: float) -> int:
    """A measured value as the coupler's 16-bit register (clamped to 0..0xFFFF)."""
    return max(0, min(0xFFFF, int(round(value * REGISTER_SCALE))))


def from_register(raw: int) -> float:
    """A 16-bit input register as the value it encodes."""
    return raw / REGISTER_SCALE
