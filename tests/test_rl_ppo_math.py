"""GAE and the PPO loss against hand-computed values; theta_t = 1 gives exactly the BC gradients."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from policy_fixtures import (  # noqa: F401  (fixtures)
    image_dataset_root,
    load_dataset,
    lowdim_dataset_root,
    make_bcrl_policy,
    whole_dataset_batch,
)

from lerobot_bcrl.rl.normalization import RewardScaler
from lerobot_bcrl.rl.ppo import PPOConfig, bcrl_loss, compute_gae, ppo_loss_terms


def test_gae_matches_a_hand_computed_trajectory():
    # One env, 3 steps, the episode ends after step 1 (index 1); gamma 0.9, lambda 0.8.
    rewards = torch.tensor([[1.0], [2.0], [3.0]])
    values = torch.tensor([[0.5], [1.0], [2.0]])
    dones = torch.tensor([[0.0], [1.0], [0.0]])
    last_values = torch.tensor([4.0])
    gamma, lam = 0.9, 0.8
    delta2 = 3.0 + gamma * 4.0 - 2.0  # 4.6
    delta1 = 2.0 - 1.0  # 1.0: no bootstrap across the episode end
    delta0 = 1.0 + gamma * 1.0 - 0.5  # 1.4
    a2 = delta2
    a1 = delta1
    a0 = delta0 + gamma * lam * a1
    advantages, returns = compute_gae(rewards, values, dones, last_values, gamma, lam)
    assert advantages[:, 0].tolist() == pytest.approx([a0, a1, a2])
    assert returns[:, 0].tolist() == pytest.approx([a0 + 0.5, a1 + 1.0, a2 + 2.0])


def test_gae_with_lambda_one_is_discounted_return_minus_value():
    rewards = torch.tensor([[1.0], [1.0], [1.0]])
    values = torch.zeros(3, 1)
    advantages, _ = compute_gae(rewards, values, torch.zeros(3, 1), torch.tensor([10.0]), 0.5, 1.0)
    assert advantages[0, 0].item() == pytest.approx(1 + 0.5 + 0.25 + 0.125 * 10)


def test_ppo_loss_terms_by_hand():
    old_log_prob = torch.zeros(3)
    new_log_prob = torch.log(torch.tensor([1.5, 0.5, 1.1]))  # ratios 1.5, 0.5, 1.1
    advantages = torch.tensor([1.0, -2.0, 3.0])
    terms = ppo_loss_terms(new_log_prob, old_log_prob, advantages, torch.tensor([1.0, 2.0, 3.0]),
                           torch.tensor([0.0, 2.0, 5.0]), clip_eps=0.2)
    # min(r*A, clip(r)*A): 1.5*1 vs 1.2*1 -> 1.2; 0.5*-2=-1 vs 0.8*-2=-1.6 -> -1.6; 1.1*3=3.3 both
    assert terms["policy_loss"].item() == pytest.approx(-(1.2 - 1.6 + 3.3) / 3)
    assert terms["value_loss"].item() == pytest.approx(0.5 * (1 + 0 + 4) / 3)
    assert terms["clipfrac"].item() == pytest.approx(2 / 3)
    ratios = np.array([1.5, 0.5, 1.1])
    assert terms["approx_kl"].item() == pytest.approx(np.mean(ratios - 1 - np.log(ratios)), rel=1e-5)


def test_clipped_ratio_gives_no_policy_gradient():
    new_log_prob = torch.tensor([math.log(2.0)], requires_grad=True)  # ratio 2 > 1.2 with a positive advantage
    terms = ppo_loss_terms(new_log_prob, torch.zeros(1), torch.ones(1), torch.zeros(1), torch.zeros(1), 0.2)
    terms["policy_loss"].backward()
    assert new_log_prob.grad.item() == 0.0


def test_reward_scaler_divides_by_return_std():
    scaler = RewardScaler(gamma=0.0, n_envs=1)  # gamma 0: the "return" is the reward itself
    rewards = np.random.default_rng(0).normal(0, 3.0, size=(5000, 1))
    scaled = scaler(rewards, np.zeros_like(rewards))
    var = float(scaler.return_stats.var)
    assert math.sqrt(var) == pytest.approx(3.0, rel=0.05)
    assert scaled[-1, 0] == pytest.approx(rewards[-1, 0] / math.sqrt(var + 1e-8))


def assert_close_to_scale(actual: torch.Tensor, expected: torch.Tensor, rtol: float, msg: str = "") -> None:
    """Equal within `rtol` of the larger of the two tensors' magnitudes (gradients summed in different orders)."""
    scale = max(float(expected.abs().max()), float(actual.abs().max()), 1e-12)
    torch.testing.assert_close(actual, expected, rtol=rtol, atol=rtol * scale, msg=msg)


def _grads(module) -> dict[str, torch.Tensor]:
    return {n: (p.grad.clone() if p.grad is not None else torch.zeros_like(p)) for n, p in module.named_parameters()}


def bcrl_policy_with_batches(dataset_root):
    """A fresh bcrl policy, its agent, the whole dataset as one demo batch, and a PPO minibatch of the policy's
    own samples with old log-probs shifted (a ratio != 1: a real PPO gradient)."""
    from lerobot_bcrl.rl.agent import BCRLAgent

    dataset = load_dataset(dataset_root)
    policy, preprocessor, _ = make_bcrl_policy(dataset)
    demo_batch = preprocessor(whole_dataset_batch(dataset))
    agent = BCRLAgent(policy, preprocessor)
    obs = {k: v for k, v in demo_batch.items() if k.startswith("observation.")}
    with torch.no_grad():
        actions, log_probs, _ = agent.sample(obs)
    n = actions.shape[0]
    minibatch = {"obs": obs, "actions": actions, "log_probs": log_probs + 0.3,
                 "advantages": torch.randn(n), "returns": torch.randn(n)}
    return policy, agent, demo_batch, minibatch


def test_theta_one_reproduces_pure_bc_gradients(lowdim_dataset_root):
    policy, agent, demo_batch, minibatch = bcrl_policy_with_batches(lowdim_dataset_root)

    policy.zero_grad()
    policy.forward(demo_batch)[0].backward()
    bc_grads = _grads(policy)

    # The critic learns while theta = 1 too: the action heads get exactly BC's gradients, the value head the
    # value loss's.
    policy.zero_grad()
    loss, metrics = bcrl_loss(agent, minibatch, demo_batch, theta=1.0, cfg=PPOConfig(), bc_forward=policy.forward)
    loss.backward()
    with_critic = _grads(policy)
    for name in with_critic:
        if any(head in name for head in ("delta_pos_head", "delta_quat_head", "gripper_head", "log_std")):
            assert_close_to_scale(with_critic[name], bc_grads[name], rtol=1e-5, msg=name)
    value_grads = [g for n, g in with_critic.items() if "value_head" in n]
    assert value_grads and all(g.abs().sum() > 0 for g in value_grads)

    policy.zero_grad()
    bcrl_loss(agent, minibatch, demo_batch, theta=0.5, cfg=PPOConfig(), bc_forward=policy.forward)[0].backward()
    mixed = _grads(policy)
    assert any(not torch.allclose(mixed[n], 0.5 * bc_grads[n]) for n in mixed)  # PPO contributes below theta = 1
    assert metrics["bc_loss"] > 0 and "policy_loss" in metrics


def test_term_gradient_norms_weigh_each_term_by_theta(lowdim_dataset_root):
    """The logged gradient norms are those of theta * L_BC and (1 - theta) * L_PPO's policy term, measured
    without touching the parameters' .grad; the BC share is 1 at theta = 1 and in between below it."""
    policy, agent, demo_batch, minibatch = bcrl_policy_with_batches(lowdim_dataset_root)
    policy.zero_grad()
    policy.forward(demo_batch)[0].backward()
    bc_norm = float(torch.sqrt(sum((g ** 2).sum() for g in _grads(policy).values())))

    policy.zero_grad()
    _, mixed = bcrl_loss(agent, minibatch, demo_batch, theta=0.25, cfg=PPOConfig(), bc_forward=policy.forward,
                         measure_gradients=True)
    assert all(p.grad is None or not p.grad.any() for p in policy.parameters())  # measuring leaves .grad alone
    assert mixed["bc_term_grad_norm"] == pytest.approx(0.25 * bc_norm, rel=1e-4)
    assert mixed["ppo_term_grad_norm"] > 0
    share = mixed["bc_term_grad_norm"] / (mixed["bc_term_grad_norm"] + mixed["ppo_term_grad_norm"])
    assert mixed["bc_grad_share"] == pytest.approx(share) and 0 < share < 1

    _, pure_bc = bcrl_loss(agent, minibatch, demo_batch, theta=1.0, cfg=PPOConfig(), bc_forward=policy.forward,
                           measure_gradients=True)
    assert pure_bc["ppo_term_grad_norm"] == 0 and pure_bc["bc_grad_share"] == 1.0
    _, unmeasured = bcrl_loss(agent, minibatch, demo_batch, theta=0.25, cfg=PPOConfig(), bc_forward=policy.forward)
    assert "bc_grad_share" not in unmeasured


def test_gradient_share_weighting_makes_theta_the_bc_share(lowdim_dataset_root):
    """With `term_weighting="gradient_share"` L_BC is rescaled to L_PPO's policy-gradient norm, so the BC term's
    measured share of the update is theta itself, and the resulting gradient is theta * scale * grad L_BC +
    (1 - theta) * grad L_PPO (+ the value loss's); at theta = 0 it is pure PPO, as with "loss"."""
    policy, agent, demo_batch, minibatch = bcrl_policy_with_batches(lowdim_dataset_root)
    share_cfg = PPOConfig(term_weighting="gradient_share")
    for theta in (0.9, 0.25):
        _, metrics = bcrl_loss(agent, minibatch, demo_batch, theta=theta, cfg=share_cfg, bc_forward=policy.forward,
                               measure_gradients=True)
        assert metrics["bc_grad_share"] == pytest.approx(theta, rel=1e-4)
        _, plain = bcrl_loss(agent, minibatch, demo_batch, theta=theta, cfg=PPOConfig(), bc_forward=policy.forward,
                             measure_gradients=True)
        assert plain["bc_grad_share"] != pytest.approx(theta, rel=1e-2)  # the paper's weighting is not the share
        ppo_norm = plain["ppo_term_grad_norm"] / (1 - theta)
        assert metrics["bc_scale"] == pytest.approx(ppo_norm / (plain["bc_term_grad_norm"] / theta), rel=1e-4)

    # The gradient the optimizer sees: the paper's mix plus theta * (scale - 1) * grad L_BC.
    theta = 0.25
    policy.zero_grad()
    bcrl_loss(agent, minibatch, demo_batch, theta=theta, cfg=PPOConfig(), bc_forward=policy.forward)[0].backward()
    plain_grads = _grads(policy)
    policy.zero_grad()
    policy.forward(demo_batch)[0].backward()
    bc_grads = _grads(policy)
    policy.zero_grad()
    loss, metrics = bcrl_loss(agent, minibatch, demo_batch, theta=theta, cfg=share_cfg, bc_forward=policy.forward)
    loss.backward()
    assert abs(metrics["bc_scale"] - 1) > 0.3  # the BC term is really re-weighted here
    for name, grad in _grads(policy).items():
        expected = plain_grads[name] + theta * (metrics["bc_scale"] - 1) * bc_grads[name]
        assert_close_to_scale(grad, expected, rtol=1e-4, msg=name)

    _, pure_ppo = bcrl_loss(agent, minibatch, demo_batch, theta=0.0, cfg=share_cfg, bc_forward=policy.forward)
    assert "bc_scale" not in pure_ppo
    with pytest.raises(ValueError, match="term_weighting"):
        PPOConfig(term_weighting="share")


def test_gradient_share_of_an_image_policy_weighs_the_layers_after_its_cnn(image_dataset_root, lowdim_dataset_root):
    """The term norms skip the image encoder (no backward pass through the CNN to measure them), the share is still
    theta on the other layers, and both terms still train the CNN; a low-dim policy's norms cover every parameter."""
    policy, agent, demo_batch, minibatch = bcrl_policy_with_batches(image_dataset_root)
    encoder_ids = {id(p) for p in policy.model.keypoint_encoder.parameters()}
    normed = agent.term_norm_parameters()
    assert encoder_ids and not encoder_ids & {id(p) for p in normed}
    assert len(normed) + len(encoder_ids) == len([p for p in policy.parameters() if p.requires_grad])
    policy.zero_grad()
    loss, metrics = bcrl_loss(agent, minibatch, demo_batch, theta=0.25, cfg=PPOConfig(term_weighting="gradient_share"),
                              bc_forward=policy.forward, measure_gradients=True)
    assert metrics["bc_grad_share"] == pytest.approx(0.25, rel=1e-4)
    loss.backward()
    assert all(p.grad is not None and p.grad.abs().sum() > 0 for p in policy.model.keypoint_encoder.cnn.parameters()
               if p.dim() > 1)  # every conv's weights learn

    lowdim_policy, lowdim_agent, _, _ = bcrl_policy_with_batches(lowdim_dataset_root)
    assert [id(p) for p in lowdim_agent.term_norm_parameters()] == [id(p) for p in lowdim_policy.parameters()]


def test_gripper_entropy_bonus_adds_its_own_gradient_and_leaves_the_log_std_alone(lowdim_dataset_root):
    policy, agent, demo_batch, minibatch = bcrl_policy_with_batches(lowdim_dataset_root)
    coef = 0.5

    def grads_with(cfg):
        policy.zero_grad()
        bcrl_loss(agent, minibatch, demo_batch, theta=0.0, cfg=cfg, bc_forward=policy.forward)[0].backward()
        return _grads(policy)

    plain, with_bonus = grads_with(PPOConfig()), grads_with(PPOConfig(gripper_entropy_coef=coef))
    policy.zero_grad()
    (-coef * agent.evaluate(minibatch["obs"], minibatch["actions"])[1]["gripper"].mean()).backward()
    bonus = _grads(policy)
    assert any(bonus[n].abs().sum() > 0 for n in bonus if "gripper_head" in n)
    for name in plain:
        assert_close_to_scale(with_bonus[name] - plain[name], bonus[name], rtol=1e-4, msg=name)
    assert torch.equal(bonus["log_std"], torch.zeros_like(bonus["log_std"]))  # the Gaussian's entropy is not in it

    class WithoutGripper:  # an agent whose action has no gripper class
        module = policy

        def evaluate(self, obs, actions):
            log_prob, entropies, value = agent.evaluate(obs, actions)
            return log_prob, {"action": sum(entropies.values())}, value

    with pytest.raises(ValueError, match="gripper class"):
        bcrl_loss(WithoutGripper(), minibatch, demo_batch, theta=0.0, cfg=PPOConfig(gripper_entropy_coef=coef))
