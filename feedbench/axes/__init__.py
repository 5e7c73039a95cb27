"""The seam where an axis kind plugs in (``[bench] axis``): one `Axis` subclass per kind and
the one registry of them, the entry-point group ``feedbench.axes``, as for the families and
the device kinds::

    [project.entry-points."feedbench.axes"]
    my_gantry = "my_lab.gantry:Gantry"

An axis kind says what differs between benches: its drives (`nodes`, the PDO maps, the EDS
of its simulated drives), the devices it needs whatever the family (`devices`, opened as a
family's are: `devices`), its own ``[bench]`` keys (`schema`, added to the
bench schema, `axis_schema`), its simulated peer (`start_simulated`) and where that peer's
devices listen (`addresses`); for the demo and a campaign, the truth of its simulated world
(`truth`), whether the report draws its recordings (`reported`) and the key of its
simulated noise's seed (`noise_seed`). `bench.Bench`, `demo` and `campaign` run the same
steps for every kind and name none (`bench.run_axis`: the kind a run config names).
"""

from __future__ import annotations

from typing import Any, ClassVar, Mapping

from feedbench.config import ConfigError, Field, registered
from feedbench.engine.plan import Plan

ENTRY_POINT_GROUP = "feedbench.axes"


class Axis:
    """One kind of axis; subclasses set `name` (the entry point's, what ``[bench] axis``
    says) and override `nodes`, `packaged_eds`, `start_simulated` and `addresses`.

    `cfg` is the validated ``[bench]`` table, `plan` the run's plan (None: no run),
    `needs` the devices the plan's experiment needs (name → settings); `self.needs` adds
    the axis's own `devices` to them."""

    name: ClassVar[str]
    schema: ClassVar[Mapping[str, Field]] = {}
    """Its own ``[bench]`` keys (e.g. a second drive's node id)."""
    devices: ClassVar[Mapping[str, Mapping[str, Any]]] = {}
    """The devices it needs whatever the family (name → settings)."""
    pdo_config: ClassVar[Any] = None
    """The PDO maps of its drives (`drivers.cia402.Cia402Drive`; None: the drive's own)."""
    stop_margin_s: ClassVar[float] = 0.25
    """Default ``[bench.stop] margin_s`` (s): how long a stop may take to stand still."""
    reported: ClassVar[bool] = False
    """The demo's report draws its recordings (`report.run_section` reads the single drive's
    channels, e.g. ``force``; say True once it draws yours)."""
    noise_seed: ClassVar[str | None] = None
    """The dotted config key of its simulated measurement noise's seed, which a campaign
    draws per run (``bench.world.noise_seed``; None: no seeded noise)."""
    default: ClassVar[bool] = False
    """The kind a ``[bench]`` table without ``axis`` runs (one registered kind says so)."""

    def __init__(self, cfg: Mapping[str, Any], plan: Plan | None,
                 needs: Mapping[str, Mapping[str, Any]]) -> None:
        self.cfg = cfg
        self.plan = plan
        self.needs = {**self.devices, **needs}

    def nodes(self) -> dict[str, int]:
        """Drive name → CANopen node id ("": the only drive)."""
        raise NotImplementedError

    @staticmethod
    def packaged_eds() -> str:
        """The EDS of its simulated drives (the default of ``[bench] eds``)."""
        raise NotImplementedError

    def served(self) -> dict[str, dict[str, Any]]:
        """The devices `feedbench sim` serves (name → settings): its own by default."""
        return dict(self.devices)

    def start_simulated(self, cycle_s: float, bus_options: Mapping[str, Any],
                        tables: Mapping[str, Mapping[str, Any]], listen: bool = False) -> Any:
        """Its simulated drives and the peers of the devices of `tables` (name → checked
        table, `devices.device_tables`) on the bench's bus; `listen`: where the
        tables' addresses say (`feedbench sim`), else on free loopback ports. The returned
        object's `close()` stops them; its `modbus_devices` are the Modbus peers served."""
        raise NotImplementedError

    @staticmethod
    def addresses(simulated: Any) -> dict[str, str]:
        """Device name → where its simulated peer listens."""
        raise NotImplementedError

    @staticmethod
    def truth(world: Mapping[str, Any]) -> dict[str, Any]:
        """The true values of the simulated world of the ``[bench.world]`` table `world` (SI),
        which the demo and a campaign hand each family's `Experiment.summary`; none by
        default."""
        return {}


def axes(distribution: str | None = None) -> dict[str, type[Axis]]:
    """Every registered axis kind by name (entry points of `ENTRY_POINT_GROUP`; of that
    installed `distribution` only, if given)."""
    return registered(ENTRY_POINT_GROUP, Axis, distribution)


def axis_kind(name: str) -> type[Axis]:
    """The registered axis kind `name`; another is a `ConfigError` naming ``bench.axis``."""
    known = axes()
    if name not in known:
        raise ConfigError(f"bench.axis: must be one of {', '.join(sorted(known))} "
                          f"(got {name!r})")
    return known[name]


def default_axis() -> str:
    """The name of the registered kind that declares itself the `Axis.default`; none or
    several (an installed package's kind declaring it too) are a `ConfigError` naming them."""
    named = sorted(name for name, cls in axes().items() if cls.default)
    if len(named) != 1:
        raise ConfigError(f"bench.axis: one installed axis kind must be the default "
                          f"(Axis.default), not {len(named)}: {', '.join(named) or 'none'}; "
                          "give bench.axis")
    return named[0]


def axis_schema() -> dict[str, Field]:
    """The ``[bench]`` keys every registered axis kind declares (`Axis.schema`); two kinds
    declaring one key are a `TypeError` naming both."""
    fields: dict[str, Field] = {}
    owner: dict[str, str] = {}
    for name, cls in axes().items():
        for key, spec in cls.schema.items():
            if key in fields:
                raise TypeError(f"bench.{key}: declared by the axis kinds {owner[key]} and "
                                f"{name}")
            fields[key], owner[key] = spec, name
    return fields
