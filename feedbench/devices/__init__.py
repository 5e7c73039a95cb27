"""The seam where a device besides the drives plugs in: one `Device` subclass per kind, and
the one registry of them, and `PerCycleDevice`, the base of the runner's per-cycle devices
(the failure rule and the every-n-cycles reading).

A device kind is what the host needs to serve one instrument every bus cycle: the schema of
its own ``[bench.devices.<name>]`` table (`Device.table_schema`: ``kind``, its ``address``
if it has one, its Modbus ``unit_id``, its own settings, `Device.schema`), and `open`, which
connects its driver at that address (or on the drives' CAN network) and returns the
runner's `CycleDevice`. A family asks for devices by name with settings
(`Experiment.devices`); an axis kind adds its own (`axes.rack_pinion.RackPinionAxis`);
`device_tables` checks their tables (unknown keys, address and unit-id collisions) before
anything opens and `open_cycle_devices` opens them; both know no kind by name. The
registry is the entry-point group ``feedbench.devices``, as for the families
(``feedbench.experiments``)::

    [project.entry-points."feedbench.devices"]
    my_probe = "my_lab.my_probe:MyProbe"

A kind's simulated peer is registered under the same name in ``feedbench.sim_devices``
(`sim_backends.process.SimulatedPeer`); a simulated bench starts the peers of the kinds a
run needs and the host reaches them at their addresses (`DeviceLinks.peers`); a device
whose table gives no address, which hardware needs, is named on stderr (`hardware_gaps`).
The ``[bench]`` keys of earlier versions (``modbus``, ``daq_port``…) are each a kind's
`Device.old_keys`: `read_old_keys` moves them into its table with a one-line hint.
docs/ARCHITECTURE.md walks through adding one.
"""

from __future__ import annotations

import json
import sys
from contextlib import ExitStack
from dataclasses import dataclass, field
from typing import Any, Callable, ClassVar, Mapping, TypeVar

from feedbench.config import ConfigError, Field, positive, registered, validate_table
from feedbench.engine.plan import Plan
from feedbench.engine.runner import CycleDevice
from feedbench.protocols.address import split_address

ENTRY_POINT_GROUP = "feedbench.devices"

T = TypeVar("T")


@dataclass(frozen=True)
class DeviceLinks:
    """What an open bench offers a device kind: `cfg`, the validated ``[bench]`` table;
    `network`, the drives' canopen network; `drives`, name → `drivers.cia402.Cia402Drive`
    ("" the only one); `stack`, which closes what a device opens; `peers`, device name →
    where its simulated peer is reached (simulated bench; used in place of the table's
    address)."""

    cfg: Mapping[str, Any]
    network: Any
    drives: Mapping[str, Any]
    stack: ExitStack
    peers: Mapping[str, str] = field(default_factory=dict)


class Device:
    """One kind of device besides the drives; subclasses set `name` (the entry point's and
    the name a family asks for), what their ``[bench.devices.<name>]`` table holds
    (`address_doc`, `unit_id`, `schema`) and override `open`."""

    name: ClassVar[str]
    address_doc: ClassVar[str] = ""
    """What its ``address`` is (host:port, serial port); "" if it has none (it is reached
    through the drives' CAN network)."""
    unit_id: ClassVar[int | None] = None
    """Its default Modbus unit id (``unit_id``); None: not a Modbus device."""
    schema: ClassVar[Mapping[str, Field]] = {}
    """Its own settings, each a key of its table; a family's settings override them."""
    old_keys: ClassVar[Mapping[str, str]] = {}
    """``[bench]`` keys of earlier versions that were its own → the key of its table."""

    @classmethod
    def table_schema(cls, name: str) -> dict[str, Field]:
        """The schema of its ``[bench.devices.<name>]`` table."""
        fields = {"kind": Field(str, name, "registered device kind (default: the table's "
                                "name)")}
        if cls.address_doc:
            fields["address"] = Field(str, "", cls.address_doc)
        if cls.unit_id is not None:
            fields["unit_id"] = Field(int, cls.unit_id, "Modbus unit id (device id)",
                                      positive)
        return {**fields, **cls.schema}

    @classmethod
    def open(cls, settings: Mapping[str, Any], links: DeviceLinks) -> CycleDevice:
        """Connect the driver with `settings` (its checked table with the family's settings
        over it, `device_table`) and return the runner's device."""
        raise NotImplementedError

    @staticmethod
    def address(settings: Mapping[str, Any]) -> str:
        """The address of `settings` (the simulated peer's on a simulated bench); empty is a
        `ConfigError` naming the field."""
        if not settings["address"]:
            raise ConfigError(f"bench.devices.{settings['name']}.address: the experiment uses "
                              f"the {settings['kind']} device; give its address")
        return settings["address"]

    @classmethod
    def modbus_client(cls, settings: Mapping[str, Any], links: DeviceLinks):
        """A Modbus TCP client at the address (host:port), closed by `links.stack`."""
        from feedbench.drivers.modbus_devices import connect_tcp

        where = f"bench.devices.{settings['name']}.address"
        client = connect_tcp(*split_address(cls.address(settings), where))
        links.stack.callback(client.close)
        return client


class PerCycleDevice:
    """A base for the runner's per-cycle devices (`runner.CycleDevice`) that holds the
    failure rule and the every-n-cycles reading, written once for every device kind.

    The failure rule: the first failure of an action run through `guarded` is raised (the
    runner aborts the run); afterwards every action is skipped and every reading is None
    (the device answers NaN), so the drives' safe stop never waits on a broken link.
    `poll` reads every `every_cycles` bus cycles, the run's first cycle included.
    Subclasses set `channels`, `units` (and `streams`) and override the steps they use;
    one that overrides `start` calls this one.
    """

    channels: tuple[str, ...] = ()
    units: dict[str, str] = {}
    streams: dict = {}

    def __init__(self, every_cycles: int = 1) -> None:
        self.every_cycles = every_cycles
        self.failed = False
        self._count = 0

    def start(self, plan: Plan, recorder) -> None:
        """Count the cycles from the run's first."""
        self._count = 0

    def before_sync(self, index: int | None) -> None:
        """Nothing to send."""

    def after_sync(self, cycle: int) -> tuple[float, ...]:
        """No per-cycle values."""
        return ()

    def stop(self, recorder) -> None:
        """Nothing to stop."""

    def guarded(self, action: Callable[[], T]) -> T | None:
        """`action()`; its first failure is raised, afterwards nothing runs (None)."""
        if self.failed:
            return None
        try:
            return action()
        except Exception:
            self.failed = True
            raise

    def poll(self, read: Callable[[], T]) -> T | None:
        """`read()` through `guarded` in every `every_cycles`-th call (one call per bus
        cycle, the first call reads); None in the cycles between and after a failure."""
        due = self._count % self.every_cycles == 0
        self._count += 1
        return self.guarded(read) if due else None


def devices(distribution: str | None = None) -> dict[str, type[Device]]:
    """Every registered device kind by name (entry points of `ENTRY_POINT_GROUP`; of that
    installed `distribution` only, if given)."""
    return registered(ENTRY_POINT_GROUP, Device, distribution)


def device_kind(name: str, table: Mapping[str, Any], declared: bool) -> type[Device]:
    """The registered kind of the device `name` (its table's ``kind``, else `name`); an
    unregistered one is a `ConfigError` naming the table (`declared`: the config has it)
    or else the experiment that needs it."""
    known = devices()
    kind = table.get("kind", name)
    if kind in known:
        return known[kind]
    if "kind" in table or declared:
        where = f"bench.devices.{name}" + (".kind" if "kind" in table else "")
        raise ConfigError(f"{where}: {kind} is not a registered device kind (known: "
                          f"{', '.join(sorted(known))})")
    raise ConfigError(f"experiment.type: needs the device {kind}, which is not registered "
                      f"(known: {', '.join(sorted(known))})")


def device_table(name: str, table: Mapping[str, Any], settings: Mapping[str, Any] = {},
                 declared: bool = True) -> dict[str, Any]:
    """The checked ``[bench.devices.<name>]`` `table` with a family's `settings` over it and
    ``name``: what `Device.open` gets; an unknown key is a `ConfigError` naming it
    (`declared`: the config has the table, `device_kind`)."""
    cls = device_kind(name, table, declared)
    checked = validate_table({**table, **settings}, cls.table_schema(name),
                             f"bench.devices.{name}")
    return {**checked, "name": name}


def device_tables(bench: Mapping[str, Any],
                  needs: Mapping[str, Mapping[str, Any]]) -> dict[str, dict[str, Any]]:
    """The devices of `needs` (name → a family's settings), checked (`device_table`) with
    those the validated ``[bench]`` table's ``devices`` declares besides; two of them at one
    address with one unit id (or none) are a `ConfigError` naming both fields, before
    anything opens. Only the devices of `needs` are returned: what the run opens."""
    declared = bench.get("devices", {})
    names = [*needs, *(name for name in declared if name not in needs)]
    tables = {name: device_table(name, declared.get(name, {}), needs.get(name, {}),
                                 name in declared)
              for name in names}
    _check_collisions(tables)
    return {name: tables[name] for name in needs}


def _check_collisions(tables: Mapping[str, Mapping[str, Any]]) -> None:
    """Two devices at one address (empty: the simulated bench's one Modbus server) with one
    unit id, or two non-Modbus devices at one address, are a `ConfigError`."""
    seen: dict[tuple[str, int | None], str] = {}
    for name, table in tables.items():
        if "address" not in table or (not table["address"] and "unit_id" not in table):
            continue
        key = (table["address"], table.get("unit_id"))
        field_name = "unit_id" if "unit_id" in table else "address"
        if key in seen:
            at = f" at {key[0]}" if key[0] and field_name == "unit_id" else ""
            raise ConfigError(f"bench.devices.{name}.{field_name}: {table[field_name]}{at} is "
                              f"also bench.devices.{seen[key]}.{field_name}")
        seen[key] = name


def read_old_keys(bench: Mapping[str, Any]) -> dict[str, Any]:
    """A ``[bench]`` table with the keys of earlier versions (each a kind's `old_keys`) moved
    into ``devices.<kind>``, one line on stderr for each saying what to write instead."""
    out = {**bench, "devices": {name: dict(table)
                                for name, table in bench.get("devices", {}).items()}}
    for name, cls in devices().items():
        for old, new in cls.old_keys.items():
            if old in out:
                value = out.pop(old)
                out["devices"].setdefault(name, {}).setdefault(new, value)
                print(f"feedbench: bench.{old} is read as bench.devices.{name}.{new}; write "
                      f"[bench.devices.{name}] {new} = {json.dumps(value)}", file=sys.stderr)
    return out


def hardware_gaps(tables: Mapping[str, Mapping[str, Any]]) -> list[str]:
    """The address fields `tables` leave empty: fine on a simulated bench, whose peers are
    reached where they listen, a `ConfigError` on hardware."""
    return [f"bench.devices.{name}.address" for name, table in tables.items()
            if "address" in table and not table["address"]]


def open_cycle_devices(tables: Mapping[str, Mapping[str, Any]],
                       links: DeviceLinks) -> list[CycleDevice]:
    """The runner's devices of `tables` (name → `device_table`), opened in that order at
    their simulated peers' addresses where there are (`links.peers`); `links.stack` closes
    them."""
    opened = []
    for name, table in tables.items():
        settings = {**table, "address": links.peers[name]} if name in links.peers else table
        opened.append(devices()[table["kind"]].open(settings, links))
    return opened
