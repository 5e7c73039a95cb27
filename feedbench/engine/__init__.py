"""The run engine, apart from the families it runs (as bluesky keeps its RunEngine apart from
its plans): `family` (the `Experiment` seam and its registry), `plan` (segments computed
before anything moves), `limits` and `preflight` (checks before motion), `runner` (the
cyclic loop, the safe stop, observers), `replay` (a recording played back through the same
observers) and `incremental` (the live analysis of the windows completed so far)."""
