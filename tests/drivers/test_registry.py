"""drivers/registry.py: one open_* per device kind, the protocol / transport looked up in a registry.

Unknown names are ConfigErrors naming the file (when loading cell.yaml), the key and the known
names; every known name opens its driver against the simulator `cell sim up` serves.
"""
from __future__ import annotations

import uuid
from contextlib import asynccontextmanager
from typing import AsyncIterator, get_args

import pytest

from controller.defaults import SIM_REPLY_TIMEOUT_MS
from core.config import (CONFIG_DIR, CellConfig, CellIOTransportName, CncProtocolName, PowerTransportName,
                         RobotProtocolName, load_cell, load_material, load_sim, parse_model)
from core.errors import ConfigError
from drivers import registry
from drivers.cellio import CellIO
from drivers.power_can import CanPowerSource
from drivers.power_modbus import ModbusPowerSource
from drivers.robot import RobotLink
from sims.clock import SimClock
from sims.up import Served, SimContext, close_all, serve_all
from sims.world import World

CELL_YAML = (CONFIG_DIR / "cell.yaml").read_text(encoding="utf-8")


@pytest.mark.parametrize("table, names", [
    (registry.ROBOT_BACKENDS, RobotProtocolName), (registry.CNC_BACKENDS, CncProtocolName),
    (registry.POWER_BACKENDS, PowerTransportName), (registry.CELLIO_BACKENDS, CellIOTransportName)])
def test_the_registries_know_exactly_the_names_cell_yaml_accepts(table, names):
    assert tuple(table) == get_args(names)


@pytest.mark.parametrize("old, new, key, known", [
    ("protocol: rlp1", "protocol: rlp2", "devices.robot.protocol", "known: rlp1"),
    ("protocol: grbl", "protocol: marlin", "devices.cnc.protocol", "known: grbl"),
    ("transport: modbus_tcp  # modbus_tcp |", "transport: profinet  #", "devices.power_source.transport",
     "known: modbus_tcp, modbus_rtu, can"),
    ("transport: modbus_tcp  # modbus_tcp (", "transport: ethercat  # (", "devices.cellio.transport",
     "known: modbus_tcp"),
])
def test_an_unknown_protocol_in_cell_yaml_names_the_file_the_key_and_the_known_ones(old, new, key, known):
    assert old in CELL_YAML
    with pytest.raises(ConfigError) as e:
        parse_model(CELL_YAML.replace(old, new, 1), CellConfig, "config/cell.yaml")
    msg = str(e.value)
    assert msg.startswith("config/cell.yaml: line ") and f"'{key}'" in msg and known in msg, msg


def test_a_robot_section_without_a_protocol_is_rlp1():
    text = CELL_YAML.replace("    protocol: rlp1", "", 1)
    assert parse_model(text, CellConfig, "cell.yaml").devices.robot.protocol == "rlp1"


@pytest.mark.parametrize("open_fn, section, field, key", [
    (registry.open_robot, "robot", "protocol", "devices.robot.protocol"),
    (registry.open_cnc, "cnc", "protocol", "devices.cnc.protocol"),
    (registry.open_power_source, "power_source", "transport", "devices.power_source.transport"),
    (registry.open_cellio, "cellio", "transport", "devices.cellio.transport"),
])
def test_open_refuses_a_name_missing_from_its_registry(open_fn, section, field, key):
    dev = getattr(load_cell().devices, section)
    bad = dev.model_construct(**{**dict(dev), field: "nope"})   # past the loader's check, as code could
    with pytest.raises(ConfigError, match=rf"'{key}': unknown .* 'nope'; known: "):
        open_fn(bad)


@asynccontextmanager
async def served(tmp_path, module: str, cell: CellConfig | None = None) -> AsyncIterator[tuple[CellConfig, Served]]:
    cell = cell or load_cell()
    ctx = SimContext(cell=cell, sim=load_sim(), world=World(tmp_path), clock=SimClock(cell.cell.time_scale),
                     log_dir=tmp_path, ephemeral=True)
    out = await serve_all(ctx, [module])
    try:
        yield cell, out[0]
    finally:
        await close_all(out)


async def test_open_robot_rlp1_talks_to_the_robot_simulator(tmp_path):
    async with served(tmp_path, "sims.robot_sim") as (cell, s):
        link = registry.open_robot(cell.devices.robot, time_scale=cell.cell.time_scale, url=s.url)
        assert type(link) is RobotLink and link.url == s.url and link.line_scale == cell.cell.time_scale
        assert link.link_timeout_s == cell.devices.robot.link_timeout_s
        try:
            st = await link.connect()
            assert st.state == "IDLE" and link.connected
            t = await link.send_move("MOVJ", 1.0, 2.0, 3.0, 0, 0, 1, 3000)
            await link.wait_executed(t, timeout=10)
            assert link.stats.heard > 0 and link.stats.bad == 0
        finally:
            await link.close()


async def test_open_cnc_grbl_talks_to_the_cnc_simulator(tmp_path):
    async with served(tmp_path, "sims.cnc") as (cell, s):
        cnc = registry.open_cnc(cell.devices.cnc, url=s.url)
        assert type(cnc).__module__ == "drivers.grbl.link" and type(cnc).__name__ == "CncLink"
        try:
            st = await cnc.connect()
            assert st.state in ("Idle", "Alarm") and cnc.connected
        finally:
            await cnc.close()


@pytest.mark.parametrize("transport, cls", [("modbus_tcp", ModbusPowerSource), ("modbus_rtu", ModbusPowerSource),
                                            ("can", CanPowerSource)])
async def test_open_power_source_by_transport_talks_to_the_power_simulator(tmp_path, transport, cls):
    cell = load_cell()
    dev = cell.devices.power_source
    upd: dict[str, object] = {"transport": transport}
    if transport == "modbus_rtu":
        upd["url"] = "socket://127.0.0.1:0"
    if transport == "can":
        upd["can"] = dev.can.model_copy(update={"interface": "virtual", "channel": f"reg-{uuid.uuid4().hex[:8]}"})
    dev = dev.model_copy(update=upd)
    cell = cell.model_copy(update={"devices": cell.devices.model_copy(update={"power_source": dev})})
    async with served(tmp_path, "sims.power_sim", cell) as (_, s):
        ps = registry.open_power_source(dev, load_material(), url=None if transport == "can" else s.url,
                                        timeout_ms=SIM_REPLY_TIMEOUT_MS)
        assert type(ps) is cls and ps.timeout_s == SIM_REPLY_TIMEOUT_MS / 1000.0
        assert not isinstance(ps, ModbusPowerSource) or ps.rtu == (transport == "modbus_rtu")
        try:
            await ps.connect()
            st = await ps.next_status()
            assert st.watchdog_echo == st.counter and ps.error is None   # the source echoed this cycle
        finally:
            await ps.close()


async def test_open_cellio_modbus_tcp_talks_to_the_cellio_simulator(tmp_path):
    async with served(tmp_path, "sims.cellio_sim") as (cell, s):
        io = registry.open_cellio(cell.devices.cellio, url=s.url, timeout_ms=SIM_REPLY_TIMEOUT_MS)
        assert type(io) is CellIO and io.lost_after_cycles == cell.devices.cellio.lost_after_cycles
        try:
            await io.connect()
            st = await io.next_inputs()
            assert st.door_closed and st.estop_released
        finally:
            await io.close()
