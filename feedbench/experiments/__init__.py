"""The experiment families, one module each (`engine.family.Experiment` subclasses, registered
under the entry-point group ``feedbench.experiments``), and `signals`, the setpoint helpers
they share. The engine that runs them lives in `feedbench.engine`."""
