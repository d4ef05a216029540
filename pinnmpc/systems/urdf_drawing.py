"""A URDF arm's stick drawing: its joint origins and tip by Pinocchio's forward kinematics."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from pinnmpc.systems.urdf import RigidArm


def stick_points(arm: RigidArm, q: np.ndarray) -> np.ndarray:
    """Joint origins and the tip, (N, n + 1, 3) in the base frame: the tip frame's origin where the arm names one,
    else the last joint plus twice its link's centre of mass offset (the link's reach, for drawing)."""
    import pinocchio as pin

    model, data = arm.pinocchio
    q = np.atleast_2d(np.asarray(q, dtype=np.float64))[:, : arm.nq]
    if arm._pin_order is not None:
        q = q[:, arm._pin_order]
    tip_id = model.getFrameId(arm.tip_frame) if arm.tip_frame else None
    reach = None if tip_id is not None else 2.0 * np.asarray(arm._nominal_pinocchio[0].inertias[arm.nq].lever)
    out = np.empty((q.shape[0], arm.nq + 2, 3))
    for i, qi in enumerate(q):
        pin.forwardKinematics(model, data, qi)
        out[i, 0] = 0.0
        out[i, 1 : arm.nq + 1] = [data.oMi[j].translation for j in range(1, arm.nq + 1)]
        if tip_id is not None:
            pin.updateFramePlacements(model, data)
            out[i, -1] = data.oMf[tip_id].translation
        else:
            out[i, -1] = out[i, -2] + data.oMi[arm.nq].rotation @ reach
    return out
