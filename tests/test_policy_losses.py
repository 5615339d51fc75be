"""BC loss terms against hand-computed values, the rotation-vector conversions against the numpy geometry, and the spatial-softmax keypoint on a synthetic image."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from lerobot_bcrl import geometry
from lerobot_bcrl.policies.bcrl import losses
from lerobot_bcrl.policies.bcrl.modeling_bcrl import (CPU_CHUNK_FRAMES, KeypointEncoder, SpatialSoftmax, quat_from_rotvec,
                                                    rotvec_from_quat)


def test_rotation_vectors_of_quaternions_match_the_numpy_geometry_and_invert():
    rng = np.random.default_rng(0)
    rotvecs = np.concatenate([rng.normal(size=(200, 3)) * 0.05, rng.normal(size=(20, 3)), np.zeros((1, 3)),
                              [[0.0, 0.0, 3.1]], [[1e-9, 0.0, 0.0]]])  # small, large, zero, near a half turn, tiny
    quats = geometry.rotvec_to_quat(rotvecs)
    quats[::2] *= -1  # either cover gives the same rotation vector
    ours = rotvec_from_quat(torch.tensor(quats, dtype=torch.float64)).numpy()
    np.testing.assert_allclose(ours, geometry.quat_to_rotvec(quats), rtol=1e-9, atol=1e-12)
    back = quat_from_rotvec(torch.tensor(rotvecs, dtype=torch.float64)).numpy()
    np.testing.assert_allclose(back, geometry.quat_canonical(geometry.rotvec_to_quat(rotvecs)), rtol=1e-9, atol=1e-12)


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


def test_keypoint_encoder_in_cpu_chunks_gives_the_one_batch_keypoints_and_gradients():
    torch.manual_seed(0)
    encoder = KeypointEncoder(3, (8, 8, 8), 4)
    images = torch.rand(CPU_CHUNK_FRAMES * 2 + 3, 3, 32, 32)  # two full chunks and a short one
    weights = torch.randn(len(images), 8)

    def keypoints_and_gradients(forward):
        encoder.zero_grad()
        keypoints = forward(images)
        (keypoints * weights).sum().backward()
        return keypoints.detach(), [p.grad.clone() for p in encoder.parameters()]

    one_batch, one_batch_grads = keypoints_and_gradients(encoder._keypoints)
    chunked, chunked_grads = keypoints_and_gradients(encoder)
    torch.testing.assert_close(chunked, one_batch, rtol=1e-5, atol=1e-6)
    with torch.no_grad():
        torch.testing.assert_close(encoder(images), one_batch, rtol=1e-5, atol=1e-6)
    # The last conv's bias has no gradient in exact arithmetic (the spatial softmax is shift-invariant per map):
    # compare every other parameter, each relative to its size.
    for (name, _), grad, expected in zip(encoder.named_parameters(), chunked_grads, one_batch_grads):
        if name != f"cnn.{len(encoder.cnn) - 1}.bias":
            assert float((grad - expected).norm()) <= 1e-4 * float(expected.norm()), name
