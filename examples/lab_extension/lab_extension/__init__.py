"""A lab's extension of feedbench (the worked example of docs/ARCHITECTURE.md, "Extending
feedbench"): the `settling_time` family, the `linear_scale` device kind and its simulated
peer, registered by entry points in this package's pyproject.toml; README.md walks through
each contract it uses."""
