"""Quaternion and delta-action maths: round trips, sign continuity, clamps."""

import math

import numpy as np
import pytest

from lerobot_bcrl import geometry as G
from lerobot_bcrl.envs import controller


def random_quats(n, seed=0):
    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_rotvec_quat_round_trip():
    rng = np.random.default_rng(1)
    rotvecs = rng.normal(size=(100, 3))
    rotvecs *= (rng.uniform(0, math.pi - 1e-3, size=100) / np.linalg.norm(rotvecs, axis=1))[:, None]
    np.testing.assert_allclose(G.quat_to_rotvec(G.rotvec_to_quat(rotvecs)), rotvecs, atol=1e-9)
    # tiny angles take the series branch
    tiny = np.array([1e-12, -2e-12, 0.0])
    np.testing.assert_allclose(G.quat_to_rotvec(G.rotvec_to_quat(tiny)), tiny, atol=1e-15)


def test_quat_multiply_matches_rotation_composition():
    a, b = np.array([0, 0, 0.3]), np.array([0, 0, -0.1])
    np.testing.assert_allclose(G.quat_to_rotvec(G.quat_multiply(G.rotvec_to_quat(a), G.rotvec_to_quat(b))), a + b)
    q = random_quats(10)
    identity = G.quat_multiply(q, G.quat_conjugate(q))
    np.testing.assert_allclose(identity, np.tile([0, 0, 0, 1.0], (10, 1)), atol=1e-12)


def test_delta_action_from_poses_round_trips_and_is_canonical():
    rng = np.random.default_rng(2)
    q_now = random_quats(50, seed=3)
    for i in range(50):
        rotvec = rng.normal(size=3)
        rotvec *= rng.uniform(0, G.MAX_DELTA_ROT_RAD * 0.99) / np.linalg.norm(rotvec)
        q_next = G.quat_multiply(G.rotvec_to_quat(rotvec), q_now[i])
        q_next *= -1 if i % 2 else 1  # either cover of the measured pose
        pos_now = rng.normal(size=3)
        pos_next = pos_now + rng.uniform(-0.02, 0.02, size=3)
        action, clamped = G.delta_action_from_poses(pos_now, q_now[i], pos_next, q_next, gripper_command=0.7)
        assert not clamped
        assert action.shape == (8,) and action[6] >= 0 and action[7] == G.GRIPPER_CLOSED
        reached_pos, reached_quat = G.apply_delta_action(pos_now, q_now[i], action)
        np.testing.assert_allclose(reached_pos, pos_next, atol=1e-12)
        assert abs(abs(np.dot(reached_quat, q_next)) - 1) < 1e-12


def test_clamps_keep_direction_and_axis():
    delta, clamped = G.clamp_delta_pos(np.array([0.3, 0.4, 0.0]))
    assert clamped and np.isclose(np.linalg.norm(delta), G.MAX_DELTA_POS_M)
    np.testing.assert_allclose(delta / np.linalg.norm(delta), [0.6, 0.8, 0.0])
    big = G.rotvec_to_quat(np.array([0.0, 0.5, 0.0]))
    q, clamped = G.clamp_delta_quat(big)
    assert clamped
    np.testing.assert_allclose(G.quat_to_rotvec(q), [0.0, G.MAX_DELTA_ROT_RAD, 0.0], atol=1e-12)
    small = G.rotvec_to_quat(np.array([0.01, 0.0, 0.0]))
    q, clamped = G.clamp_delta_quat(-small)  # the negative cover comes back canonical
    assert not clamped and q[3] > 0
    np.testing.assert_allclose(q, small)


def test_slerp_endpoints_and_midpoint():
    q0 = G.IDENTITY_QUAT_XYZW
    q1 = G.rotvec_to_quat(np.array([0.0, 0.0, 1.0]))
    np.testing.assert_allclose(G.quat_slerp(q0, q1, 0.0), q0, atol=1e-12)
    np.testing.assert_allclose(G.quat_slerp(q0, q1, 1.0), q1, atol=1e-12)
    np.testing.assert_allclose(G.quat_to_rotvec(G.quat_slerp(q0, -q1, 0.5)), [0, 0, 0.5], atol=1e-12)


@pytest.mark.parametrize("bad", [np.zeros(4), np.array([np.nan, 0, 0, 1.0])])
def test_bad_quaternions_raise(bad):
    with pytest.raises(ValueError, match="quaternion"):
        G.quat_normalize(bad)


def test_controller_conversion_round_trip_and_clamp():
    rng = np.random.default_rng(4)
    for _ in range(100):
        ctrl = np.concatenate([rng.uniform(-0.5, 0.5, 3), rng.uniform(-0.08, 0.08, 3), [rng.choice([-1.0, 1.0])]])
        action, clamped = controller.controller_to_delta_action(ctrl)
        assert not clamped
        back, _ = controller.delta_action_to_controller(action)
        np.testing.assert_allclose(back, ctrl, atol=1e-9)
    # a full-scale command is beyond the paper's feasible range and gets clamped
    action, clamped = controller.controller_to_delta_action(np.array([1.0, 1.0, 1.0, 1.0, 0, 0, -1]))
    assert clamped
    assert np.linalg.norm(action[:3]) <= G.MAX_DELTA_POS_M + 1e-12
    assert G.quat_angle(action[3:7]) <= G.MAX_DELTA_ROT_RAD + 1e-9
    assert action[7] == G.GRIPPER_OPEN
    # an all-zero quaternion from an untrained policy means "no rotation", not a crash
    ctrl, _ = controller.delta_action_to_controller(np.zeros(8))
    np.testing.assert_allclose(ctrl[:6], 0.0)
    with pytest.raises(ValueError, match="non-finite"):
        controller.delta_action_to_controller(np.full(8, np.nan))


def test_quat_rotate_and_pose_compose_inverse_round_trip():
    # 90 degrees about z takes x to y
    q_z90 = G.rotvec_to_quat(np.array([0.0, 0.0, math.pi / 2]))
    np.testing.assert_allclose(G.quat_rotate(q_z90, [1.0, 0.0, 0.0]), [0.0, 1.0, 0.0], atol=1e-12)
    rng = np.random.default_rng(5)
    q = random_quats(20, seed=6)
    p = rng.normal(size=(20, 3))
    v = rng.normal(size=(20, 3))
    # rotating preserves length and matches two successive rotations
    np.testing.assert_allclose(np.linalg.norm(G.quat_rotate(q, v), axis=1), np.linalg.norm(v, axis=1))
    np.testing.assert_allclose(
        G.quat_rotate(G.quat_multiply(q, q[::-1]), v), G.quat_rotate(q, G.quat_rotate(q[::-1], v)), atol=1e-12
    )
    inv_p, inv_q = G.pose_inverse(p, q)
    ident_p, ident_q = G.pose_compose(p, q, inv_p, inv_q)
    np.testing.assert_allclose(ident_p, 0.0, atol=1e-12)
    np.testing.assert_allclose(np.abs(ident_q[:, 3]), 1.0, atol=1e-12)


def test_quat_continuous_removes_sign_jumps():
    angles = np.linspace(0, 1.0, 10)
    quats = G.rotvec_to_quat(np.stack([np.zeros(10), np.zeros(10), angles], axis=1))
    flipped = quats * np.where(np.arange(10) % 3 == 1, -1.0, 1.0)[:, None]
    np.testing.assert_allclose(G.quat_continuous(flipped), quats, atol=1e-12)


def test_cube_yaw_error_wraps_every_90_degrees_and_ignores_the_gripper_pointing_down():
    down = G.rotvec_to_quat(np.array([math.pi, 0.0, 0.0]))  # a gripper pointing at the table
    for eef_yaw_deg, cube_yaw_deg, expected_deg in [(0, 10, 10), (0, 80, -10), (30, 0, -30), (0, 44, 44), (0, 46, -44),
                                                     (-170, 100, 0), (20, 200, 0)]:
        eef = G.quat_multiply(G.rotvec_to_quat(np.array([0.0, 0.0, math.radians(eef_yaw_deg)])), down)
        cube = G.rotvec_to_quat(np.array([0.0, 0.0, math.radians(cube_yaw_deg)]))
        assert math.degrees(G.cube_yaw_error(eef, cube)) == pytest.approx(expected_deg, abs=1e-6), (eef_yaw_deg, cube_yaw_deg)
        turned = G.quat_multiply(G.rotvec_to_quat(np.array([0.0, 0.0, G.cube_yaw_error(eef, cube)])), eef)
        assert G.cube_yaw_error(turned, cube) == pytest.approx(0.0, abs=1e-6)  # the error is the turn that aligns
