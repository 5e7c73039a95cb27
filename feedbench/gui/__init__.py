"""Live window (pyqtgraph + PySide6) and the results it draws while a run acquires.

`feedbench.gui.live_results` (and `live_structure`, the tool-tip and SMFE families) need no
Qt; `feedbench.gui.live_window` imports PySide6.
"""
