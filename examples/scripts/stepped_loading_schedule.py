"""Stepped loading of the rack-and-pinion axis with a load schedule of the script's own.

The schedule — which motor is loaded alone, the coupled preload levels, the step and the
depth into the bumper — is built here from the command line instead of a config file.
Prints the stiffness per loaded motor (N/µm, Eq. 3.26) and per preload level the force at
which the preload is lost (N, Ch. 3.4.3)::

    python examples/scripts/stepped_loading_schedule.py --preloads 6 18 --single master
"""

from __future__ import annotations

import argparse
import tomllib
from pathlib import Path

import feedbench
from feedbench.units import N_PER_UM

CONFIG = Path(__file__).parents[2] / "feedbench" / "examples" / "stepped_loading.toml"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default=CONFIG, help="rack-and-pinion bench config (TOML)")
    parser.add_argument("--single", nargs="*", default=["master", "slave"],
                        help="motors loaded alone (k_m, k_s)")
    parser.add_argument("--preloads", type=float, nargs="*", default=[6.0, 12.0, 18.0],
                        help="coupled loading at these preloads (%% of the rated torque)")
    parser.add_argument("--step-um", type=float, default=12.5, help="position step (µm)")
    parser.add_argument("--depth-um", type=float, default=300.0, help="deepest command (µm)")
    parser.add_argument("--measure-s", type=float, default=0.2, help="window per step (s)")
    parser.add_argument("--setup-s", type=float, default=2.0,
                        help="standstill after each change of coupling or preload (s)")
    parser.add_argument("--load-cell-every", type=int, default=2,
                        help="read the load cell every n bus cycles")
    args = parser.parse_args()

    config = tomllib.loads(Path(args.config).read_text(encoding="utf-8"))
    config["bench"].setdefault("devices", {}).setdefault("load_cell", {})["every_cycles"] = \
        args.load_cell_every

    schedule = {"backlash": [], "single_motor": args.single, "preload_pct": args.preloads,
                "step_um": args.step_um, "single_step_um": args.step_um,
                "depth_um": args.depth_um, "single_depth_um": args.depth_um + 50.0,
                "measure_s": args.measure_s, "settle_s": 0.05, "setup_s": args.setup_s,
                "unload": False}
    with feedbench.open_bench(config) as bench:
        bench.drive.enable()
        run = bench.run("stepped_loading", **schedule)
        channels = [channel for device in bench.devices for channel in device.channels]
    print(f"device_channels = {','.join(channels)}")
    print(f"run = {run.id} ({run.status}, {run.path})")
    for motor, fit in run.result["stiffness"].items():
        print(f"k_{motor}_N_um = {fit['k_N_m'] / N_PER_UM:.3f}")
    for level in run.result["preload"]:
        name = f"preload_{level['preload_pct']:g}"
        if "error" in level:
            print(f"{name}: {level['error']}")
        else:
            print(f"{name}.loss_force_N = {level['loss_force_N']:.1f}")
            print(f"{name}.torque_share = {level['torque_share']:.3f}")


if __name__ == "__main__":
    main()
