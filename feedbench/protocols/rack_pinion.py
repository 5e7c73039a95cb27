"""Objects of the rack-and-pinion axis's two CiA 402 drives (master and slave node).

Both nodes load `rack_pinion.eds` (the simulated drive's EDS plus the objects below). The
axis controller (the CNC's master–slave coupling, Fig. 3.2) answers on the master node;
each node reports its own motor encoder. Units at the rack, like the CiA 402 objects:
0x6076 is the rated torque expressed as a force at the rack (mN), so 0x6071 / 0x6077 and
the preload level are per mille of the rated torque.
"""

from __future__ import annotations

PRELOAD_LEVEL = 0x2040
"""UNSIGNED16, ‰ of the rated torque: the tension torque τ_p (Eq. 3.1)."""
WEIGHT_MASTER = 0x2041
"""REAL32: torque weighting factor K_Tm (Fig. 3.2)."""
WEIGHT_SLAVE = 0x2042
"""REAL32: torque weighting factor K_Ts."""
COUPLING = 0x2043
"""UNSIGNED8: 0 master–slave with preload, 1 master alone, 2 slave alone (Ch. 3.4)."""
PRELOAD_GAIN = 0x2044
"""REAL32, (m/s)/N at the rack: K_p of the torque-equalisation PI (Eq. 3.10)."""
PRELOAD_INTEGRAL_TIME = 0x2045
"""REAL32, s: T_i of the torque-equalisation PI."""
LOAD_POSITION = 0x2050
"""INTEGER32, nm: the linear scale (x_load), PDO-mappable."""
MOTOR_POSITION = 0x2051
"""INTEGER32, nm: this node's motor encoder expressed at the rack (x_m or x_s), PDO-mappable."""

COUPLINGS = {"coupled": 0, "master": 1, "slave": 2}
"""Coupling mode names (config, plan settings) → 0x2043 values."""

AXIS_TPDO = (MOTOR_POSITION, LOAD_POSITION)
"""TPDO 3 of each node: motor encoder and linear scale (8 bytes)."""
