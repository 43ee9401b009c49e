"""How the published VPACE/LfGP expert data (utiasSTARS/vpace `expert_data/`) map onto this env.

Observations: dims 0:53 of our 59-dim Panda play observation are the VPACE-era 53-dim layout in
the same frame and units (checked in tests/test_vpace_consistency.py): they map one to one.
Actions: (dx, dy, dz, gripper) with the same scaling, but the published gripper command closes
on > 0 (the reference code's convention) while ours opens on > 0 (thesis appendix A.1, docs/panda_play.md): the gripper
dimension is negated on import.
"""

from __future__ import annotations

import numpy as np

GRIPPER_DIM = 3


def vpace_action_to_shiftkit(action: np.ndarray) -> np.ndarray:
    """Published VPACE action(s), shape (..., 4), in this env's convention (a new array)."""
    a = np.array(action, copy=True)
    if a.shape[-1:] != (4,):
        raise ValueError(f"VPACE Panda play actions have 4 dims (dx, dy, dz, gripper), got shape {a.shape}")
    a[..., GRIPPER_DIM] = -a[..., GRIPPER_DIM]
    return a
