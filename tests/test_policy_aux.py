"""The auxiliary targets (`aux.*`) survive LeRobot's preprocessor and reach `BCRLPolicy.forward` unchanged.

LeRobot's batch->transition converter drops unknown keys; processor_bcrl keeps `aux.*` (see its docstring).
"""

from __future__ import annotations

import pytest
import torch
from policy_fixtures import load_dataset, lowdim_dataset_root, make_bcrl_policy  # noqa: F401

from lerobot_bcrl.features import ACTION_KEY, AUX_EEF_POS_KEY, AUX_GRASP_POS_KEY, AUX_GRASP_VALID_KEY, AUX_IMITATE_KEY

AUX_KEYS = (AUX_EEF_POS_KEY, AUX_GRASP_POS_KEY, AUX_GRASP_VALID_KEY)


def raw_batch(dataset, batch_size=8):
    return next(iter(torch.utils.data.DataLoader(dataset, batch_size=batch_size, shuffle=True)))


def aux_seen_by_forward(policy, batch) -> dict:
    """Run forward and capture the aux tensors the loss received."""
    seen = {}
    original = policy._aux_terms

    def spy(outputs, batch_in_forward):
        seen.update({k: batch_in_forward[k].clone() for k in AUX_KEYS})
        return original(outputs, batch_in_forward)

    policy._aux_terms = spy
    _, metrics = policy.forward(batch)
    return seen, metrics


def test_aux_targets_reach_forward_through_a_fresh_preprocessor(lowdim_dataset_root):
    dataset = load_dataset(lowdim_dataset_root)
    policy, preprocessor, _ = make_bcrl_policy(dataset)
    raw = raw_batch(dataset)
    seen, metrics = aux_seen_by_forward(policy, preprocessor(dict(raw)))
    for key in AUX_KEYS:
        assert torch.equal(seen[key], raw[key]), key
    # the grasp label is the EEF position at the first closed-gripper frame of the episode
    assert seen[AUX_GRASP_VALID_KEY].all()
    assert metrics["bc_aux_eef_mse"] > 0 and metrics["bc_aux_grasp_mse"] > 0


def test_aux_targets_reach_forward_through_a_saved_and_reloaded_preprocessor(lowdim_dataset_root, tmp_path):
    """The resume path: lerobot-train reloads the pipeline with LeRobot's own batch_to_transition."""
    from lerobot.policies.factory import make_pre_post_processors

    dataset = load_dataset(lowdim_dataset_root)
    policy, preprocessor, postprocessor = make_bcrl_policy(dataset)
    preprocessor.save_pretrained(tmp_path)
    postprocessor.save_pretrained(tmp_path)
    reloaded, _ = make_pre_post_processors(policy.config, pretrained_path=str(tmp_path))
    raw = raw_batch(dataset)
    seen, _ = aux_seen_by_forward(policy, reloaded(dict(raw)))
    for key in AUX_KEYS:
        assert torch.equal(seen[key], raw[key]), key


def test_aux_loss_uses_the_targets_and_masks_invalid_grasps(lowdim_dataset_root):
    dataset = load_dataset(lowdim_dataset_root)
    policy, preprocessor, _ = make_bcrl_policy(dataset)
    batch = preprocessor(raw_batch(dataset))
    outputs = policy.model(batch)
    eef_target = (batch[AUX_EEF_POS_KEY] - policy.aux_pos_mean) / policy.aux_pos_std
    expected_eef = (outputs.eef_pos_normalized - eef_target).pow(2).mean()
    _, metrics = policy.forward(batch)
    assert metrics["bc_aux_eef_mse"] == pytest.approx(expected_eef.item(), rel=1e-5)
    # a batch whose grasps are all invalid contributes no grasp loss, however wrong the targets
    batch[AUX_GRASP_VALID_KEY] = torch.zeros_like(batch[AUX_GRASP_VALID_KEY])
    batch[AUX_GRASP_POS_KEY] = batch[AUX_GRASP_POS_KEY] + 100.0
    _, metrics = policy.forward(batch)
    assert metrics["bc_aux_grasp_mse"] == 0.0


def test_missing_aux_targets_fail_loudly(lowdim_dataset_root):
    dataset = load_dataset(lowdim_dataset_root)
    policy, preprocessor, _ = make_bcrl_policy(dataset)
    batch = {k: v for k, v in preprocessor(raw_batch(dataset)).items() if not k.startswith("aux.")}
    with pytest.raises(KeyError, match="auxiliary targets"):
        policy.forward(batch)
    policy.config.require_aux_targets = False
    _, metrics = policy.forward(batch)
    assert "bc_aux_eef_mse" not in metrics


def test_bc_loss_skips_frames_flagged_not_to_imitate(lowdim_dataset_root):
    """Frames of a planned miss (aux.imitate False) change neither the loss nor its gradient."""
    dataset = load_dataset(lowdim_dataset_root)
    policy, preprocessor, _ = make_bcrl_policy(dataset)
    batch = preprocessor(raw_batch(dataset, batch_size=16))
    assert batch[AUX_IMITATE_KEY].all()  # the fixture dataset has no planned misses
    keep = torch.arange(16) % 3 != 0
    flagged = dict(batch, **{AUX_IMITATE_KEY: keep[:, None]})
    flagged[ACTION_KEY] = torch.where(keep[:, None], batch[ACTION_KEY], -batch[ACTION_KEY])  # wrong labels
    flagged[AUX_GRASP_POS_KEY] = torch.where(keep[:, None], batch[AUX_GRASP_POS_KEY], batch[AUX_GRASP_POS_KEY] + 1)
    subset = {k: v[keep] if isinstance(v, torch.Tensor) and len(v) == 16 else v for k, v in batch.items()}

    def loss_and_grad(b):
        policy.zero_grad()
        loss, _ = policy.forward(b)
        loss.backward()
        return loss.item(), torch.cat([p.grad.flatten() for p in policy.parameters() if p.grad is not None])

    loss_flagged, grad_flagged = loss_and_grad(flagged)
    loss_subset, grad_subset = loss_and_grad(subset)
    # the same wrong labels, all flagged to imitate: they do count (so the check above is not vacuous)
    loss_unmasked, _ = loss_and_grad(dict(flagged, **{AUX_IMITATE_KEY: torch.ones(16, 1, dtype=torch.bool)}))
    assert loss_flagged == pytest.approx(loss_subset, rel=1e-5)
    # The two batches sum in different orders (multi-threaded BLAS picks its kernels by shape): float32
    # rounding, relative to the largest gradient (~1e-7 of it); a flagged frame that counted, or a mean over
    # all 16 frames, moves the gradient by a third of it or more.
    torch.testing.assert_close(grad_flagged, grad_subset, rtol=1e-4, atol=1e-5 * grad_subset.abs().max().item())
    assert loss_unmasked > 2 * loss_subset  # 4.6-6.5x over five random batches and inits
    nothing = dict(batch, **{AUX_IMITATE_KEY: torch.zeros(16, 1, dtype=torch.bool)})
    loss_none, grad_none = loss_and_grad(nothing)
    assert loss_none == 0.0 and not grad_none.any()


def test_the_aux_patch_refuses_a_lerobot_it_was_not_written_for(monkeypatch):
    import lerobot

    from lerobot_bcrl.policies.bcrl.aux_targets import LEROBOT_VERSION, keep_aux_targets_in_batches

    keep_aux_targets_in_batches()  # the pinned version: fine, and idempotent
    monkeypatch.setattr(lerobot, "__version__", "0.7.0")
    with pytest.raises(RuntimeError, match=f"lerobot=={LEROBOT_VERSION} \\(found 0.7.0\\)"):
        keep_aux_targets_in_batches()
