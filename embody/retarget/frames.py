"""The fixed change of axes between the body (SMPL-X) and the robot torso frame."""

from __future__ import annotations

import numpy as np

#: SMPL-X is y-up, facing +z, left = +x; the robot torso frame is x forward, y left, z up.
#: Rows: robot x = body z, robot y = body x, robot z = body y.
BODY_TO_ROBOT = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
