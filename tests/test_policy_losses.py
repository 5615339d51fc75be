"""BC loss terms against hand-computed values, and the spatial-softmax keypoint on a synthetic image."""

from __future__ import annotations

import math

import pytest
import torch

from lerobot_bcrl.policies.bcrl import losses
from lerobot_bcrl.policies.bcrl.modeling_bcrl import SpatialSoftmax


def test_quaternion_distance_is_zero_for_both_covers():
    q = torch.nn.functional.normalize(torch.tensor([[0.1, -0.2, 0.3, 0.9], [0.5, 0.5, -0.5, 0.5]]), dim=-1)
    # float32 rounding of 1 - |q . q| on unit quaternions: a few 1e-7; -q without the |.| would give 2
    assert losses.quaternion_distance(q, q).item() == pytest.approx(0.0, abs=1e-5)
    assert losses.quaternion_distance(-q, q).item() == pytest.approx(0.0, abs=1e-5)


def test_quaternion_distance_of_a_half_turn_is_one_minus_cos_quarter_turn():
    identity = torch.tensor([[0.0, 0.0, 0.0, 1.0]])
    about_z = torch.tensor([[0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)]])  # 90 degrees
    assert losses.quaternion_distance(about_z, identity).item() == pytest.approx(1 - math.cos(math.pi / 4))


def test_quaternion_sign_penalty_only_on_negative_w():
    quats = torch.tensor([[0.0, 0.0, 0.6, 0.8], [0.0, 0.0, -0.6, -0.8]])
    assert losses.quaternion_sign_penalty(quats[:1]).item() == 0.0
    assert losses.quaternion_sign_penalty(quats).item() == pytest.approx(0.8 / 2)


def test_cosine_distance_of_opposite_aligned_and_orthogonal_directions():
    v = torch.tensor([[1.0, 2.0, -0.5]])
    assert losses.cosine_distance(-3 * v, v).item() == pytest.approx(2.0)
    assert losses.cosine_distance(0.1 * v, v).item() == pytest.approx(0.0, abs=1e-5)
    assert losses.cosine_distance(torch.tensor([[0.0, 1.0, 0.0]]), torch.tensor([[1.0, 0.0, 0.0]])).item() == (
        pytest.approx(1.0)
    )


def test_class_weighted_cross_entropy_matches_manual_computation():
    logits = torch.tensor([[2.0, -1.0], [0.5, 0.3], [-1.0, 1.5]])
    target = torch.tensor([0, 1, 1])
    weights = torch.tensor([0.25, 3.0])
    nll = [-torch.log_softmax(logits[i], -1)[target[i]] for i in range(3)]
    manual = sum(weights[target[i]] * nll[i] for i in range(3)) / weights[target].sum()
    assert losses.gripper_cross_entropy(logits, target, weights).item() == pytest.approx(manual.item(), rel=1e-5)
    # and it differs from the unweighted mean, so the weights do something
    unweighted = sum(nll) / 3
    assert abs(manual.item() - unweighted.item()) > 1e-3


def test_balanced_class_weights_from_closed_fraction():
    # a quarter of the frames closed: 0.25 * w_closed == 0.75 * w_open == 0.5
    weights = losses.balanced_class_weights(0.25)
    assert weights.tolist() == pytest.approx([0.5 / 0.75, 2.0])
    # a dataset that never closes gets a large but finite weight
    assert torch.isfinite(losses.balanced_class_weights(0.0, min_fraction=0.01)).all()


def test_l1_l2_and_masked_mse():
    pred, target = torch.tensor([[1.0, -1.0]]), torch.tensor([[0.0, 1.0]])
    assert losses.l1_loss(pred, target).item() == pytest.approx(1.5)
    assert losses.l2_loss(pred, target).item() == pytest.approx(2.5)
    pred = torch.tensor([[1.0, 1.0, 1.0], [5.0, 5.0, 5.0]])
    target = torch.zeros(2, 3)
    assert losses.masked_mse(pred, target, torch.tensor([[True], [False]])).item() == pytest.approx(1.0)
    assert losses.masked_mse(pred, target, torch.tensor([[False], [False]])).item() == 0.0


@pytest.mark.parametrize(("row", "col"), [(3, 10), (0, 0), (15, 7)])
def test_spatial_softmax_finds_one_bright_spot(row, col):
    height, width = 16, 12
    image = torch.zeros(1, 1, height, width)
    image[0, 0, row, col] = 50.0  # a bright pixel: the softmax puts all its mass there
    keypoint = SpatialSoftmax(learnable_temperature=False)(image)[0, 0]
    expected_x = -1 + 2 * col / (width - 1)
    expected_y = -1 + 2 * row / (height - 1)
    assert keypoint.tolist() == pytest.approx([expected_x, expected_y], abs=1e-4)
