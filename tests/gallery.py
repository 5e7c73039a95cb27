"""The gallery of real measurements from other labs (`tests/data/gallery.toml`): what each
dataset holds and how the closure is to be run on it. Shared by
`tests/test_closure_gallery.py` and `benchmarks/bench_closure_real.py`."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from feedbench.config import read_toml

DATA = Path(__file__).resolve().parent / "data"
GALLERY = DATA / "gallery.toml"


@dataclass(frozen=True)
class Dataset:
    """One dataset of the gallery.

    fit / validation: CSV recordings with their sidecars (validation None: the closure holds
    out the last part of `fit`, as the model's `holdout_fraction` says); model: the declared
    base model; key: the effect its authors document, a name of the closure's vocabulary;
    held_out: kept out of all tuning, reported apart; recordings: per CSV file name, what it
    holds once read (samples, sample_rate_Hz, and [min, max] of position, force and
    external_force in SI).
    """

    name: str
    fit: Path
    validation: Path | None
    model: Path
    key: str
    held_out: bool
    recordings: dict[str, dict[str, Any]] = field(default_factory=dict)

    @property
    def files(self) -> list[Path]:
        """The recordings, fit first."""
        return [self.fit] + ([self.validation] if self.validation else [])


def datasets() -> list[Dataset]:
    """Every dataset of `gallery.toml`, in its order."""
    out = []
    for name, entry in read_toml(GALLERY).items():
        folder = DATA / name
        validation = entry.get("validation")
        out.append(Dataset(name, folder / entry["fit"],
                           folder / validation if validation else None,
                           folder / entry["model"], entry["key"], entry["held_out"],
                           entry["recordings"]))
    return out
