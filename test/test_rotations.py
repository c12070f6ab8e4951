"""The scalar attitude helpers the nodes use per message agree with the rotation matrix."""

from __future__ import annotations

import math

import numpy as np
import pytest

from vehicle_estimation.estimators.common.rotations import (gravity_on_body_y, quat_from_euler, quat_to_rotmat,
                                                             yaw_of_quat)


@pytest.mark.parametrize("rpy", [(0.0, 0.0, 0.0), (0.05, -0.02, 1.2), (-0.3, 0.4, -2.9), (0.1, 1.2, 3.1)])
def test_yaw_and_lateral_gravity_match_the_rotation_matrix(rpy):
    q = quat_from_euler(*rpy)
    r = quat_to_rotmat(q)
    assert yaw_of_quat(*q) == pytest.approx(math.atan2(r[1, 0], r[0, 0]), abs=1e-12)
    assert gravity_on_body_y(*q) == pytest.approx(r[2, 1], abs=1e-12)
    # any norm: a message's quaternion need not be normalised
    assert yaw_of_quat(*(3.0 * np.asarray(q))) == pytest.approx(yaw_of_quat(*q), abs=1e-12)


def test_degenerate_quaternions_give_nan():
    assert math.isnan(yaw_of_quat(0.0, 0.0, 0.0, 0.0))
    assert math.isnan(gravity_on_body_y(0.0, 0.0, 0.0, 0.1))
    assert math.isnan(gravity_on_body_y(math.nan, 0.0, 0.0, 1.0))
