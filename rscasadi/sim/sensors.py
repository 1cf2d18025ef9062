"""The sensors of a simulated arm: absolute encoders on the link and on the motor."""
from __future__ import annotations

import numpy as np

LINK_COUNTS, MOTOR_COUNTS = 2 ** 19, 2 ** 17       # per turn: the link, the motor before the gear


def quanta(gear_ratio) -> tuple:
    """The smallest steps (rad) of the link encoder and of the motor encoder seen at the slow side."""
    return 2 * np.pi / LINK_COUNTS, 2 * np.pi / MOTOR_COUNTS / np.asarray(gear_ratio, float)
