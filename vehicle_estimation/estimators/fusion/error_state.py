"""The layout of the fusion's error state (paper 003 Eq. (32)) and the filter's phases."""

from __future__ import annotations

# Error-state layout, Eq. (32): z = [dp, dv, eps, dba, dbg], then the mounting pitch and
# yaw corrections dm (about base_link y, z; R_m,true = (I + S([0, dm])) R_m,hat).
IP, IV, IA, IBA, IBG, IM = 0, 3, 6, 9, 12, 15
N_ERR = 17

# Phases of :attr:`FusionEKF.status`, in order: alignment (Sec. 7.1), then the free heading
# until GNSS motion fixes the yaw, then running.
STATUS_WAIT_STANDSTILL = "waiting_for_standstill"
STATUS_ALIGNING = "aligning"
STATUS_WAIT_HEADING = "waiting_for_heading"
STATUS_RUNNING = "running"
