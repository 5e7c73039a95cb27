"""Chirp into the drive at three velocity-loop gains, the servo mobilities overlaid.

The issue asks for three preloads; a preload exists only on the rack-and-pinion axis,
where only the stepped loading commands it (and the chirp analyses the single drive's
force, which that axis records per motor). So the setting varied here is the velocity-loop
gain K_p: the mobility motor force → motor velocity is the mechanics' own, so f_t and f_r
(Eqs. 4.13, 4.14) should not move with the gain, while the controller's force changes.
Prints f_t, f_r (Hz) and the coherence per gain; writes the overlay as a PNG::

    python examples/scripts/chirp_three_gains.py [--gains 6000 9000 13000] [--repetitions 4]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402

import feedbench  # noqa: E402

HERE = Path(__file__).parent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default=HERE / "lab_bench.toml", help="bench config (TOML)")
    parser.add_argument("--gains", type=float, nargs=3, default=[6000.0, 9000.0, 13000.0],
                        help="velocity-loop gains K_p (N·s/m)")
    parser.add_argument("--duration-s", type=float, default=4.0, help="one sweep (s)")
    parser.add_argument("--repetitions", type=int, default=4, help="sweeps averaged")
    args = parser.parse_args()

    figure, axes = plt.subplots(figsize=(8, 4.5))
    with feedbench.open_bench(args.config) as bench:
        bench.drive.enable()
        for gain in args.gains:
            bench.drive.set_gains(K_p_Ns_m=gain)
            run = bench.run("chirp", duration_s=args.duration_s, repetitions=args.repetitions)
            r = run.result
            print(f"K_p {gain:g}: run = {run.id}")
            print(f"K_p {gain:g}: f_t_Hz = {r['antiresonance_hz']:.2f}")
            print(f"K_p {gain:g}: f_r_Hz = {r['resonance_hz']:.2f}")
            print(f"K_p {gain:g}: min_coherence = {r['min_coherence']:.4f}")
            axes.semilogy(r["frf"]["f_hz"], r["frf"]["H1_abs"], label=f"K_p = {gain:g} N·s/m")
        plot = bench.output_dir / "chirp_three_gains.png"
    axes.set_xlabel("frequency (Hz)")
    axes.set_ylabel("|H1| motor velocity / motor force ((m/s)/N)")
    axes.grid(alpha=0.3, which="both")
    axes.legend()
    figure.savefig(plot, dpi=100)
    print(f"plot = {plot}")


if __name__ == "__main__":
    main()
