"""Live window (pyqtgraph + PySide6) and the results it draws while a run acquires.

`feedbench.gui.live_results` needs no Qt; `feedbench.gui.live_window` imports PySide6.
"""
