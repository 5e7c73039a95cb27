"""The lab's tests use feedbench's testing kit: the simulated bench, recording to tmp_path."""

from feedbench.testing import simulated_bench  # noqa: F401  (the pytest fixture)
