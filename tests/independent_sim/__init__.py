"""An independent closed-loop feed-drive simulator for judging the closure (issue 13).

It shares no code with feedbench (nothing here imports it): n-mass chains in continuous
state space discretized exactly, a sampled P-PI cascade at 4 kHz / 1 kHz, a force delay, the
drive's force averaged over each 1 kHz cycle, encoder quantization and noise, and each
effect written from its physics. `CASES` lists every case; `recordings` returns a case's two
recordings (in memory), `write_case` writes them (CSV + sidecar) and its declared model (TOML).
"""

from .cases import CASES, CaseFiles, CaseSpec, model_config, recordings, write_case

__all__ = ["CASES", "CaseFiles", "CaseSpec", "model_config", "recordings", "write_case"]
