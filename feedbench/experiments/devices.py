"""The seam where a device besides the drives plugs in: one `Device` subclass per kind, and
the one registry of them, and `PerCycleDevice`, the base of the runner's per-cycle devices
(the failure rule and the every-n-cycles reading).

A device kind is what the host needs to serve one instrument every bus cycle: the
``[bench]`` key of its address (`address_key`), and `open`, which connects its driver at
that address (or on the drives' CAN network) and returns the runner's `CycleDevice`.
A family asks for kinds by name with settings (`Experiment.devices`); an axis kind adds
its own (`rack_pinion_bench.RackPinionAxis`); `open_cycle_devices` opens them all and
knows none by name. The registry is the entry-point group ``feedbench.devices``, as for
the families (``feedbench.experiments``)::

    [project.entry-points."feedbench.devices"]
    my_probe = "my_lab.my_probe:MyProbe"

A kind's simulated peer is registered under the same name in ``feedbench.sim_devices``
(`sim_backends.process.SimulatedPeer`); a simulated bench starts the peers of the kinds a
run needs and puts their addresses in `DeviceLinks.cfg` in place of the configured ones.
docs/ARCHITECTURE.md walks through adding one.
"""

from __future__ import annotations

from contextlib import ExitStack
from dataclasses import dataclass
from typing import Any, Callable, ClassVar, Mapping, TypeVar

from feedbench.config import ConfigError, registered
from feedbench.experiments.plan import Plan
from feedbench.experiments.runner import CycleDevice
from feedbench.protocols.address import split_address

ENTRY_POINT_GROUP = "feedbench.devices"

T = TypeVar("T")


@dataclass(frozen=True)
class DeviceLinks:
    """What an open bench offers a device kind: `cfg`, the validated ``[bench]`` table with
    the simulated peers' addresses in place of the configured ones; `network`, the drives'
    canopen network; `drives`, name → `drivers.cia402.Cia402Drive` ("" the only one);
    `stack`, which closes what a device opens."""

    cfg: Mapping[str, Any]
    network: Any
    drives: Mapping[str, Any]
    stack: ExitStack


class Device:
    """One kind of device besides the drives; subclasses set `name` (the entry point's and
    the name a family asks for) and `address_key`, and override `open`."""

    name: ClassVar[str]
    address_key: ClassVar[str] = ""
    """The ``[bench]`` key holding where it is reached (host:port, serial port); "" none."""

    @classmethod
    def open(cls, settings: Mapping[str, Any], links: DeviceLinks) -> CycleDevice:
        """Connect the driver with the family's `settings` and return the runner's device."""
        raise NotImplementedError

    @classmethod
    def address(cls, links: DeviceLinks) -> str:
        """The configured (or simulated) address; empty is a `ConfigError` naming the key."""
        found = links.cfg.get(cls.address_key, "")
        if not found:
            raise ConfigError(f"bench.{cls.address_key}: the experiment uses the {cls.name} "
                              "device; give its address")
        return found

    @classmethod
    def modbus_client(cls, links: DeviceLinks):
        """A Modbus TCP client at the address (host:port), closed by `links.stack`."""
        from feedbench.drivers.modbus_devices import connect_tcp

        client = connect_tcp(*split_address(cls.address(links), f"bench.{cls.address_key}"))
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


def devices() -> dict[str, type[Device]]:
    """Every registered device kind by name (entry points of `ENTRY_POINT_GROUP`)."""
    return registered(ENTRY_POINT_GROUP, Device)


def open_cycle_devices(needs: Mapping[str, Mapping[str, Any]],
                       links: DeviceLinks) -> list[CycleDevice]:
    """The runner's devices of `needs` (kind name → its settings), opened in that order;
    `links.stack` closes them."""
    known = devices()
    unknown = sorted(set(needs) - set(known))
    if unknown:
        raise ConfigError(f"experiment.type: needs the device {', '.join(unknown)}, which is "
                          f"not registered (known: {', '.join(sorted(known))})")
    return [known[name].open(settings, links) for name, settings in needs.items()]
