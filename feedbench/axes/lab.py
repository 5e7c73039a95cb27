"""The lab axis (``axis = "lab"``): one linear drive and the devices its experiment needs."""

from __future__ import annotations

from typing import Any, Mapping

from feedbench.axes import Axis


class LabAxis(Axis):
    """The wiring of ``axis = "lab"`` (`axes.Axis`): one linear drive (``node_id``) and the
    devices the plan's experiment needs (`needs`, name → settings: `devices`).
    Simulated: the drive and the simulated peers of those devices
    (`sim_backends.process.SimulatedBench`, the workpiece prepared as planned)."""

    name = "lab"
    default = True
    reported = True
    noise_seed = "bench.world.noise_seed"
    stop_margin_s = 0.25
    """Default ``[bench.stop] margin_s`` (s): after its quick-stop ramp the simulated lab axis
    creeps down through the Stribeck region under velocity control; stopped from 25 mm/min it
    stood (|v| < 5 mm/min for 10 cycles) after 51 cycles, from a 500 mm/min chirp after 13."""

    def nodes(self) -> dict[str, int]:
        """Drive name → CANopen node id ("": the only drive)."""
        return {"": self.cfg["node_id"]}

    @staticmethod
    def packaged_eds() -> str:
        """The simulated drive's EDS."""
        from feedbench.sim_backends.eds import packaged_eds_path

        return str(packaged_eds_path())

    def served(self) -> dict[str, dict[str, Any]]:
        """Every device with a registered simulated peer: `feedbench sim` serves them all."""
        from feedbench.sim_backends.process import simulated_peers

        return {name: {} for name in simulated_peers()}

    def start_simulated(self, cycle_s: float, bus_options: Mapping[str, Any],
                        tables: Mapping[str, Mapping[str, Any]], listen: bool = False):
        """The simulated drive and its devices' peers on the bench's bus; `close()` stops
        them."""
        from feedbench.sim_backends.process import LOOPBACK, SimulatedBench, modbus_listen

        workpiece = self.plan.params.get("workpiece", ()) if self.plan is not None else ()
        modbus = modbus_listen(tables) if listen else (LOOPBACK, 0)
        return SimulatedBench(self.cfg, tables, workpiece, bus_options=bus_options,
                              modbus_address=modbus)

    @staticmethod
    def addresses(simulated: Any) -> dict[str, str]:
        """Device name → where its simulated peer listens."""
        return simulated.addresses

    @staticmethod
    def truth(world: Mapping[str, Any]) -> dict[str, Any]:
        """The simulated world's truth (`sim_backends.world.world_truth`; the peers' own
        tables left out); with a milling world also its modal structure (tool rows 0–2,
        workpiece 3–5)."""
        from feedbench.sim_backends.process import simulated_peers
        from feedbench.sim_backends.smfe_world import build_process
        from feedbench.sim_backends.world import world_truth

        truth = world_truth({key: table for key, table in world.items()
                             if key not in simulated_peers()})
        if "milling" in world:
            truth["milling_structure"] = build_process(world["milling"])[0].structure
        return truth
