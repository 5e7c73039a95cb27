"""feedbench: bench driver and data acquisition for machine-tool feed drives."""
__version__ = "0.1.0"
