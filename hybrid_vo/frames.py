"""Input and output records of the hybrid odometer (plain dataclasses, no ROS types)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray


@dataclass(frozen=True)
class StereoFrame:
    """One synchronized rectified stereo pair.

    Attributes:
        left, right: ``uint8`` images, ``(H, W)`` grayscale or ``(H, W, 3)`` BGR, at the
            resolution of the camera's intrinsics.
        stamp_ns: capture time.
    """

    left: NDArray[np.uint8]
    right: NDArray[np.uint8]
    stamp_ns: int
