"""Each registered thing owns its config (issue 27 item 1): a device kind the schema of its
``[bench.devices.<name>]`` table, an axis kind its ``[bench]`` keys; the bench schema is
assembled from the registries. A lab's device kind, installed at runtime with its
simulated peer, is configured only through its own table; an unknown key is refused naming
it; two devices at one address with one unit id are refused before anything opens; the
``[bench]`` keys of earlier versions are read with one line saying what to write instead;
no device, axis or family name is special-cased outside its own module (over the source).
"""

from __future__ import annotations

import ast
import inspect
import textwrap
import uuid
from pathlib import Path

import pytest

import feedbench
from feedbench.axes import axes
from feedbench.bench import Bench, bench_table, parse_run_config
from feedbench.config import OWN_DISTRIBUTION, ConfigError, read_toml, registered
from feedbench.devices import device_tables, devices, hardware_gaps
from feedbench.engine.family import families
from feedbench.sim_backends.process import SIM_PEER_GROUP, simulated_peers

PACKAGE = Path(feedbench.__file__).parent
EXAMPLES = PACKAGE / "examples"

LAB_MODULE = '''
"""A lab's Modbus thermometer (one INT16 register, 0.1 °C) and its simulated peer."""
from feedbench.config import Field
from feedbench.drivers.modbus_devices import ModbusDevice
from feedbench.devices import Device, PerCycleDevice
from feedbench.protocols.modbus_registers import Register, RegisterMap
from feedbench.sim_backends.modbus_devices import InvalidWrite, SimulatedModbusDevice
from feedbench.sim_backends.process import SimulatedPeer

MAP = RegisterMap("thermometer", (Register("temperature", 0, "INT16", 0.1, "degC"),))


class Temperature(PerCycleDevice):
    channels = ("thermometer.temperature",)
    units = {"thermometer.temperature": "degC"}

    def __init__(self, device, offset_C):
        super().__init__()
        self.device, self.offset_C = device, offset_C

    def after_sync(self, cycle):
        return (self.poll(lambda: self.device.read(MAP["temperature"])) + self.offset_C,)


class Thermometer(Device):
    name = "thermometer"
    address_doc = "host:port of the thermometer's Modbus TCP server"
    unit_id = 7
    schema = {"offset_C": Field(float, 0.0, "calibration offset (degC)")}

    @classmethod
    def open(cls, settings, links):
        device = ModbusDevice(cls.modbus_client(settings, links), settings["unit_id"], MAP)
        return Temperature(device, settings["offset_C"])


class SimulatedThermometer(SimulatedModbusDevice):
    register_map = MAP

    def __init__(self, device_id, temperature_C):
        super().__init__(device_id)
        self.temperature_C = temperature_C

    def advance(self, dt_s):
        pass

    def values(self):
        return {"temperature": self.temperature_C}

    def apply(self, name, value):
        raise InvalidWrite(name)


class ThermometerPeer(SimulatedPeer):
    name = "thermometer"
    world_schema = {"temperature_C": Field(float, 20.0, "the room's temperature (degC)")}

    def __init__(self, sim, settings):
        super().__init__(sim, settings)
        sim.serve_modbus(SimulatedThermometer(settings["unit_id"], self.world["temperature_C"]),
                         settings["name"])
'''


@pytest.fixture
def lab_thermometer(tmp_path, monkeypatch):
    """A lab's package installed for one test: its module and its metadata with the two
    entry points (the kind and its simulated peer), as pip leaves them."""
    (tmp_path / "lab_thermo.py").write_text(LAB_MODULE)
    metadata = tmp_path / "lab_thermo-1.0.dist-info"
    metadata.mkdir()
    (metadata / "METADATA").write_text("Metadata-Version: 2.1\nName: lab-thermo\nVersion: 1.0\n")
    (metadata / "entry_points.txt").write_text(
        "[feedbench.devices]\nthermometer = lab_thermo:Thermometer\n\n"
        f"[{SIM_PEER_GROUP}]\nthermometer = lab_thermo:ThermometerPeer\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    registered.cache_clear()
    yield
    registered.cache_clear()


def _bench(**keys) -> dict:
    """A checked simulated lab [bench] table on its own virtual channel."""
    return bench_table({"channel": f"tables-{uuid.uuid4().hex[:8]}", **keys})


def test_a_lab_device_is_configured_by_its_own_table(lab_thermometer, capsys):
    """The lab's kind, asked for by name, opened from its tables alone: its unit id (9, not
    its default 7) reaches both the host and the simulated peer, its own setting the host,
    its peer's world table the peer; the simulated run says on one line which address
    hardware would need."""
    bench = _bench(devices={"thermometer": {"unit_id": 9, "offset_C": 1.0}},
                   world={"thermometer": {"temperature_C": 21.5}})
    with Bench(bench, None, {"thermometer": {}}) as opened:
        device, = opened.devices
        assert opened.simulated.modbus_devices[0].device_id == 9
        assert device.after_sync(1) == (pytest.approx(22.5),)
    assert capsys.readouterr().err.splitlines() == [
        "feedbench: simulated bench: bench.devices.thermometer.address not given (the "
        "simulated peers' used); hardware needs them"]


def test_a_lab_device_table_is_checked_by_its_kinds_schema(lab_thermometer):
    tables = device_tables(_bench(devices={"thermometer": {"address": "10.0.0.5:502"}}),
                           {"thermometer": {}})
    assert tables == {"thermometer": {"kind": "thermometer", "address": "10.0.0.5:502",
                                      "unit_id": 7, "offset_C": 0.0, "name": "thermometer"}}
    assert hardware_gaps(tables) == []
    with pytest.raises(ConfigError, match=r"^bench.devices.thermometer.offset_K: unknown key "
                                          r"\(known: address, kind, offset_C, unit_id\)$"):
        device_tables(_bench(devices={"thermometer": {"offset_K": 1.0}}), {"thermometer": {}})


def test_an_unknown_key_is_refused_naming_it():
    raw = read_toml(EXAMPLES / "smfe.toml")
    raw["bench"]["devices"] = {"spindle": {"adress": "10.0.0.5:502"}}
    with pytest.raises(ConfigError, match=r"^bench.devices.spindle.adress: unknown key "
                                          r"\(known: address, kind, readback_cycles, "
                                          r"unit_id\)$"):
        parse_run_config(raw)
    raw["bench"] = {"temp_sensor": "192.168.0.30:502"}
    with pytest.raises(ConfigError, match=r"^bench.temp_sensor: unknown key \(known: axis, "):
        parse_run_config(raw)
    raw["bench"] = {"devices": {"thermometer": {}}}
    with pytest.raises(ConfigError, match=r"^bench.devices.thermometer: thermometer is not a "
                                          r"registered device kind \(known: axis_settings, "):
        parse_run_config(raw)


def test_collisions_are_refused_naming_both_fields():
    """One Modbus unit id twice at one address (also the simulated bench's one server, no
    address given), one serial port twice: refused by the config check, before anything
    opens."""
    raw = read_toml(EXAMPLES / "smfe.toml")
    raw["bench"]["devices"] = {"load_cell": {"unit_id": 1}}
    with pytest.raises(ConfigError, match=r"^bench.devices.load_cell.unit_id: 1 is also "
                                          r"bench.devices.spindle.unit_id$"):
        parse_run_config(raw)
    raw["bench"]["devices"] = {"spindle": {"address": "10.0.0.5:502"},
                               "load_cell": {"address": "10.0.0.5:502", "unit_id": 1}}
    with pytest.raises(ConfigError, match=r"^bench.devices.load_cell.unit_id: 1 at "
                                          r"10.0.0.5:502 is also bench.devices.spindle.unit_id$"):
        parse_run_config(raw)
    raw["bench"]["devices"] = {"daq": {"address": "/dev/ttyACM0"},
                               "daq2": {"kind": "daq", "address": "/dev/ttyACM0"}}
    with pytest.raises(ConfigError, match=r"^bench.devices.daq2.address: /dev/ttyACM0 is also "
                                          r"bench.devices.daq.address$"):
        parse_run_config(raw)
    raw["bench"]["devices"] = {"load_cell": {"address": "10.0.0.6:502", "unit_id": 1}}
    parse_run_config(raw)  # another address: another server


def test_an_old_config_is_read_with_one_line_per_key(capsys):
    """``modbus``, ``daq_port``, ``io_node_id``, ``load_cell``, ``load_cell_every``: each
    read into its device's table, one line on stderr saying what to write instead."""
    bench = _bench(modbus="10.0.0.5:502", daq_port="/dev/ttyACM0", io_node_id=23,
                   load_cell="10.0.0.5:502", load_cell_every=4)
    assert bench["devices"] == {"spindle": {"address": "10.0.0.5:502"},
                                "daq": {"address": "/dev/ttyACM0"},
                                "exciter": {"node_id": 23},
                                "load_cell": {"address": "10.0.0.5:502", "every_cycles": 4}}
    assert sorted(capsys.readouterr().err.splitlines()) == [
        'feedbench: bench.daq_port is read as bench.devices.daq.address; write '
        '[bench.devices.daq] address = "/dev/ttyACM0"',
        'feedbench: bench.io_node_id is read as bench.devices.exciter.node_id; write '
        '[bench.devices.exciter] node_id = 23',
        'feedbench: bench.load_cell is read as bench.devices.load_cell.address; write '
        '[bench.devices.load_cell] address = "10.0.0.5:502"',
        'feedbench: bench.load_cell_every is read as bench.devices.load_cell.every_cycles; '
        'write [bench.devices.load_cell] every_cycles = 4',
        'feedbench: bench.modbus is read as bench.devices.spindle.address; write '
        '[bench.devices.spindle] address = "10.0.0.5:502"']
    assert device_tables(bench, {"load_cell": {}})["load_cell"]["every_cycles"] == 4


def test_a_peer_owns_its_world_table(lab_thermometer):
    """``[bench.world.<name>]``: the simulated device's constants, checked by its peer's
    schema (an unknown key named), and the lab axis's own keys beside them."""
    bench = _bench(world={"load_cell": {"range_N": 5000.0}, "m_mot_kg": 30.0})
    with Bench(bench, None, {"load_cell": {}}) as opened:
        assert opened.simulated.peers["load_cell"].load_cell.range_N == 5000.0
        assert opened.simulated.drive.simulator.axis.m_mot == 30.0
    bench = _bench(world={"thermometer": {"temperature_K": 294.0}})
    with pytest.raises(ConfigError, match=r"^bench.world.thermometer.temperature_K: unknown "
                                          r"key \(known: temperature_C\)$"):
        Bench(bench, None, {"thermometer": {}}).__enter__()


def test_the_rack_and_pinion_axis_starts_the_registered_peers_the_run_needs(lab_thermometer,
                                                                          capsys):
    """Its simulated peer starts the peers of its own devices (the load cell, reading the
    bumper) and of any device the run needs (a lab's thermometer) as the lab axis does; the
    world key of earlier versions is read into the load cell's own table with one line."""
    bench = _bench(axis="rack_pinion", devices={"thermometer": {"unit_id": 9}},
                   world={"load_cell_range_N": 5000.0, "thermometer": {"temperature_C": 23.0}})
    with Bench(bench, None, {"thermometer": {}}) as opened:
        assert set(opened.simulated.peers) == {"load_cell", "thermometer"}
        assert opened.simulated.peers["load_cell"].load_cell.range_N == 5000.0
        assert sorted(d.device_id for d in opened.simulated.modbus_devices) == [2, 9]
        thermometer = next(d for d in opened.devices if d.channels == (
            "thermometer.temperature",))
        assert thermometer.after_sync(1) == (pytest.approx(23.0),)
    assert ("feedbench: bench.world.load_cell_range_N is read as bench.world.load_cell.range_N; "
            "write [bench.world.load_cell] range_N = 5000.0") in capsys.readouterr().err


def test_axis_kinds_are_registered_with_their_own_keys():
    assert {name: kind.name for name, kind in axes(OWN_DISTRIBUTION).items()} == {
        "lab": "lab", "rack_pinion": "rack_pinion"}
    assert _bench(axis="rack_pinion")["slave_node_id"] == 2
    with pytest.raises(ConfigError, match=r"^bench.axis: must be one of lab, rack_pinion "
                                          r"\(got 'gantry'\)$"):
        _bench(axis="gantry")


# -- no name special-cased outside its own module -------------------------------------------

def _string_constants(path: Path) -> set[str]:
    """Every string literal of a module, docstrings left out."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    docstrings = {id(node.body[0].value) for node in ast.walk(tree)
                  if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef,
                                       ast.AsyncFunctionDef))
                  and node.body and isinstance(node.body[0], ast.Expr)}
    return {node.value for node in ast.walk(tree) if isinstance(node, ast.Constant)
            and isinstance(node.value, str) and id(node) not in docstrings}


def _module_path(cls: type) -> Path:
    return Path(inspect.getfile(cls)).resolve()


def _named_outside(things: dict[str, set[Path]], root: Path = PACKAGE) -> list[str]:
    """``module: name`` for each name of `things` (name → the modules allowed to name it)
    that a string literal of another module under `root` (feedbench) names."""
    return sorted(f"{path.relative_to(root)}: {name}"
                  for path in root.rglob("*.py")
                  for name in _string_constants(path) & set(things)
                  if path.resolve() not in things[name])


def _family_modules() -> set[Path]:
    """The families (and the part the three tool-tip families share): they name the devices
    and the axes they need (`Experiment.devices`, `Experiment.axes`, their examples), as a
    config does."""
    return {_module_path(cls) for cls in families(OWN_DISTRIBUTION).values()} | {
        (PACKAGE / "experiments" / "tool_tip.py").resolve()}


def test_no_device_name_outside_its_own_modules():
    """A device kind is named by its host module and its peer's (and by the families and
    axes that need it, declaring so); nowhere else."""
    peers = simulated_peers()
    allowed = {name: {_module_path(kind), *([_module_path(peers[name])] if name in peers
                                            else [])} | _family_modules()
               for name, kind in devices(OWN_DISTRIBUTION).items()}
    for axis in axes(OWN_DISTRIBUTION).values():
        for name in axis.devices:
            allowed[name].add(_module_path(axis))
    assert _named_outside(allowed) == []


def test_no_axis_name_outside_its_own_module():
    allowed = {name: {_module_path(kind)} | _family_modules()
               for name, kind in axes(OWN_DISTRIBUTION).items()}
    assert _named_outside(allowed) == []


def test_no_family_name_outside_its_own_module():
    allowed = {name: {_module_path(cls)} for name, cls in families(OWN_DISTRIBUTION).items()}
    assert _named_outside(allowed) == []


def test_the_source_check_sees_a_name_special_cased(tmp_path):
    """The check itself: a module comparing with a device's name is found, a docstring
    naming it is not."""
    (tmp_path / "probe.py").write_text(textwrap.dedent('''
        """A probe of the spindle."""
        def f(kind):
            return kind == "spindle"
    '''))
    (tmp_path / "told.py").write_text('"""spindle"""\n')
    allowed = {"spindle": {_module_path(devices()["spindle"])}}
    assert _named_outside(allowed, tmp_path) == ["probe.py: spindle"]
