"""Live window (pyqtgraph + PySide6): traces, progress and the experiment family's result
while a run acquires. The result itself is the family's own analysis
(`feedbench.experiments.incremental.LiveAnalysis`) drawn from its `views.panels`.
"""
