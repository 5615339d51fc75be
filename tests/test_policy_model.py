"""The `bcrl` policy on tiny recorded datasets: action format, PPO's view of it (rl/agent.py), save/load,
overfitting, and a dataset of another layout."""

from __future__ import annotations

import pytest
import torch
from policy_fixtures import (  # noqa: F401  (fixtures)
    image_dataset_root,
    load_dataset,
    lowdim_dataset_root,
    make_bcrl_policy,
    whole_dataset_batch,
)

from lerobot_bcrl.geometry import MAX_DELTA_ROT_RAD
from lerobot_bcrl.policies.bcrl.configuration_bcrl import BCRLConfig
from lerobot_bcrl.policies.bcrl.modeling_bcrl import BCRLPolicy, rotvec_from_quat
from lerobot_bcrl.rl.agent import BCRLAgent


def assert_valid_actions(actions: torch.Tensor):
    assert actions.shape[-1] == 8
    assert torch.allclose(actions[:, 3:7].norm(dim=-1), torch.ones(len(actions)), atol=1e-5)
    assert (actions[:, 6] >= 0).all()
    assert set(actions[:, 7].tolist()) <= {-1.0, 1.0}
    assert (actions[:, :3].norm(dim=-1) <= 0.05 + 1e-6).all()
    assert (2 * torch.atan2(actions[:, 3:6].norm(dim=-1), actions[:, 6]) <= MAX_DELTA_ROT_RAD + 1e-6).all()


@pytest.mark.parametrize("fixture_name", ["lowdim_dataset_root", "image_dataset_root"])
def test_select_action_is_a_valid_deterministic_action(fixture_name, request):
    dataset = load_dataset(request.getfixturevalue(fixture_name))
    policy, preprocessor, postprocessor = make_bcrl_policy(dataset)
    assert policy.config.uses_images == (fixture_name == "image_dataset_root")
    batch = preprocessor(whole_dataset_batch(dataset))
    actions = postprocessor(policy.select_action(batch))
    assert actions.shape == (len(dataset), 8)
    assert_valid_actions(actions)
    assert torch.equal(actions, postprocessor(policy.select_action(batch)))


def test_agent_scores_the_raw_sample_it_drew_and_the_env_gets_its_projection(lowdim_dataset_root):
    dataset = load_dataset(lowdim_dataset_root)
    policy, preprocessor, _ = make_bcrl_policy(dataset)
    policy.log_std.data.fill_(0.0)  # wide enough that some samples leave the clamps
    agent = BCRLAgent(policy, preprocessor)
    batch = preprocessor(whole_dataset_batch(dataset))
    torch.manual_seed(0)
    with torch.no_grad():  # as the rollout workers sample
        raw_actions, log_prob, value = agent.sample(batch)
    env_actions = agent.to_env_action(raw_actions)
    assert_valid_actions(env_actions)
    scaled = torch.cat([env_actions[:, :3] / policy.config.delta_pos_scale_m,
                        rotvec_from_quat(env_actions[:, 3:7]) / policy.config.delta_rot_scale_rad], dim=-1)
    assert not torch.allclose(scaled, raw_actions[:, :6], atol=1e-4)  # the clamps did something
    inside = (raw_actions[:, :3].norm(dim=-1) * policy.config.delta_pos_scale_m <= policy.config.max_delta_pos_m) & (
        raw_actions[:, 3:6].norm(dim=-1) * policy.config.delta_rot_scale_rad <= MAX_DELTA_ROT_RAD)
    assert inside.any()  # and where they did nothing, the env gets the sample itself
    torch.testing.assert_close(scaled[inside], raw_actions[inside, :6], rtol=1e-4, atol=1e-5)
    new_log_prob, entropies, new_value = agent.evaluate(batch, raw_actions)
    assert log_prob.shape == entropies["continuous"].shape == entropies["gripper"].shape == value.shape == (len(dataset),)
    torch.testing.assert_close(new_log_prob, log_prob, rtol=1e-5, atol=1e-5 * float(log_prob.abs().max()))
    torch.testing.assert_close(new_value, value, rtol=1e-5, atol=1e-5 * float(value.abs().max()))
    # the log-prob is the Gaussian's at the raw sample: recomputed by hand from the mean and the std
    with torch.no_grad():
        continuous, gripper = policy.action_distributions(policy.model(batch))
        std = policy.log_std.exp()
    mean = continuous.loc
    by_hand = (-0.5 * ((raw_actions[:, :6] - mean) / std) ** 2 - std.log() - 0.5 * torch.log(torch.tensor(2 * torch.pi))).sum(-1)
    by_hand = by_hand + gripper.logits.log_softmax(-1).gather(1, raw_actions[:, 6:].long()).squeeze(1)
    torch.testing.assert_close(new_log_prob.detach(), by_hand, rtol=1e-4, atol=1e-4 * float(by_hand.abs().max()))
    # each part's entropy by hand: the Gaussian's sum over its 6 dims, the gripper class's -sum p log p
    gaussian = 6 * 0.5 * torch.log(torch.tensor(2 * torch.pi * torch.e)) + std.log().sum()
    torch.testing.assert_close(entropies["continuous"].detach(), gaussian.expand(len(dataset)), rtol=1e-5, atol=1e-6)
    p = gripper.logits.softmax(-1)
    torch.testing.assert_close(entropies["gripper"].detach(), -(p * p.log()).sum(-1), rtol=1e-4, atol=1e-6)
    # gradients reach the learned log-std and the value head
    (-(new_log_prob.mean()) - sum(entropies.values()).mean() + new_value.pow(2).mean()).backward()
    assert policy.log_std.grad is not None and policy.model.value_head.weight.grad is not None


def test_agent_takes_the_workers_noise_for_its_gaussian_part(lowdim_dataset_root):
    """Given noise (colored, from the rollout workers), the sample is mean + std * noise on the position and
    rotation and still scored by the policy's own log-prob."""
    dataset = load_dataset(lowdim_dataset_root)
    policy, preprocessor, _ = make_bcrl_policy(dataset)
    agent = BCRLAgent(policy, preprocessor)
    batch = preprocessor(whole_dataset_batch(dataset))
    noise = torch.linspace(-2.0, 2.0, len(dataset) * agent.noise_dims).reshape(len(dataset), agent.noise_dims)
    with torch.no_grad():
        torch.manual_seed(0)
        raw_actions, log_prob, _ = agent.sample(batch, noise)
        torch.manual_seed(0)
        white_actions, _, _ = agent.sample(batch)
        continuous, _ = policy.action_distributions(policy.model(batch))
        new_log_prob, _, _ = agent.evaluate(batch, raw_actions)
    assert agent.noise_dims == 6
    torch.testing.assert_close(raw_actions[:, :6], continuous.mean + policy.log_std.exp() * noise)
    torch.testing.assert_close(new_log_prob, log_prob, rtol=1e-5, atol=1e-5 * float(log_prob.abs().max()))
    assert not torch.allclose(raw_actions[:, :6], white_actions[:, :6])


@pytest.mark.parametrize("fixture_name", ["lowdim_dataset_root", "image_dataset_root"])
def test_separate_critic_keeps_the_value_loss_off_the_actor(fixture_name, request):
    dataset = load_dataset(request.getfixturevalue(fixture_name))
    policy, preprocessor, _ = make_bcrl_policy(dataset, critic_hidden_dims=(32, 32))
    assert policy.model.value_head is None
    agent = BCRLAgent(policy, preprocessor)
    batch = preprocessor(whole_dataset_batch(dataset))
    _, _, value = agent.evaluate(batch, agent.sample(batch)[0])
    assert value.shape == (len(dataset),)
    value.pow(2).mean().backward()
    grads = {name: p.grad for name, p in policy.named_parameters()}
    critic = [name for name in grads if name.startswith("model.critic.")]
    assert critic and all(grads[name] is not None and grads[name].abs().sum() > 0 for name in critic)
    actor = [name for name in grads if name not in critic]
    assert any("keypoint_encoder" in name for name in actor) == (fixture_name == "image_dataset_root")
    assert all(grads[name] is None or not grads[name].any() for name in actor), "value loss reached the actor"


def test_privileged_critic_reads_the_simulator_state_and_the_actor_acts_without_it(image_dataset_root):
    from lerobot_bcrl.features import ENV_STATE_KEY, IMAGE_KEY

    dataset = load_dataset(image_dataset_root)
    policy, preprocessor, _ = make_bcrl_policy(dataset, critic_hidden_dims=(32,), critic_observation="privileged")
    assert policy.model.critic is None and policy.model.value_head is None
    agent = BCRLAgent(policy, preprocessor)
    batch = preprocessor(whole_dataset_batch(dataset))
    value = agent.value(batch)
    # the value follows the environment state and not the camera
    assert not torch.allclose(agent.value({**batch, ENV_STATE_KEY: batch[ENV_STATE_KEY].flip(0)}), value)
    torch.testing.assert_close(agent.value({**batch, IMAGE_KEY: batch[IMAGE_KEY].flip(0)}), value)
    # the value loss trains the privileged critic only
    _, _, value = agent.evaluate(batch, agent.sample(batch)[0])
    value.pow(2).mean().backward()
    grads = {name: p.grad for name, p in policy.named_parameters()}
    critic = [name for name in grads if name.startswith("model.privileged_critic.")]
    assert critic and all(grads[name] is not None and grads[name].abs().sum() > 0 for name in critic)
    assert all(grads[name] is None or not grads[name].any() for name in grads if name not in critic)
    # deployment: a robot gives no environment state, and acting needs none
    without_state = {key: v for key, v in batch.items() if key != ENV_STATE_KEY}
    assert torch.equal(policy.select_action(without_state), policy.select_action(batch))
    assert policy.model(without_state).value is None
    # but PPO cannot go on without a value: a clear error, not a None in the advantages
    for needs_value in (agent.value, agent.sample, lambda obs: agent.evaluate(obs, agent.sample(batch)[0])):
        with pytest.raises(ValueError, match=f"privileged critic reads '{ENV_STATE_KEY}'"):
            needs_value(without_state)


def test_privileged_critic_is_refused_where_it_cannot_mean_anything(lowdim_dataset_root):
    dataset = load_dataset(lowdim_dataset_root)
    with pytest.raises(ValueError, match="give critic_hidden_dims"):
        make_bcrl_policy(dataset, critic_observation="privileged")
    with pytest.raises(ValueError, match="for pixels policies"):
        make_bcrl_policy(dataset, critic_hidden_dims=(32,), critic_observation="privileged")


def test_privileged_critic_on_a_pixels_dataset_without_environment_state_is_refused(image_dataset_root):
    from lerobot_bcrl.features import ENV_STATE_KEY

    dataset = load_dataset(image_dataset_root)
    features = {key: value for key, value in dataset.meta.features.items() if key != ENV_STATE_KEY}
    dataset.meta.info.features = features  # a camera dataset recorded without the simulator's object state
    assert ENV_STATE_KEY not in dataset.meta.features
    policy, _, _ = make_bcrl_policy(dataset, critic_hidden_dims=(32,))  # its actor needs no environment state
    assert ENV_STATE_KEY not in policy.config.input_features
    with pytest.raises(ValueError, match=f"reads '{ENV_STATE_KEY}': the dataset lacks it"):
        make_bcrl_policy(dataset, critic_hidden_dims=(32,), critic_observation="privileged")


def test_bc_checkpoint_loads_with_a_fresh_separate_critic(lowdim_dataset_root, tmp_path):
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import make_policy

    dataset = load_dataset(lowdim_dataset_root)
    policy, preprocessor, _ = make_bcrl_policy(dataset)
    policy.save_pretrained(tmp_path)
    # what `bcrl-finetune --policy.path=<BC> --policy.critic_hidden_dims=[64]` does (strict=False: a fresh critic)
    cfg = PreTrainedConfig.from_pretrained(tmp_path, cli_overrides=["--critic_hidden_dims=[64]"])
    cfg.pretrained_path, cfg.device = tmp_path, "cpu"
    assert cfg.critic_hidden_dims == (64,)
    loaded = make_policy(cfg, ds_meta=dataset.meta)
    assert loaded.model.critic is not None and loaded.model.value_head is None
    batch = preprocessor(whole_dataset_batch(dataset))
    assert torch.equal(policy.select_action(dict(batch)), loaded.select_action(dict(batch)))  # the actor is BC's


def test_gripper_class_weights_come_from_the_dataset_stats(lowdim_dataset_root):
    dataset = load_dataset(lowdim_dataset_root)
    policy, _, _ = make_bcrl_policy(dataset)
    actions = torch.stack([dataset[i]["action"] for i in range(len(dataset))])
    closed_fraction = (actions[:, 7] > 0).float().mean().item()
    weights = policy.gripper_class_weights
    assert weights.tolist() == pytest.approx([0.5 / (1 - closed_fraction), 0.5 / closed_fraction], rel=1e-4)


@pytest.mark.parametrize("fixture_name", ["lowdim_dataset_root", "image_dataset_root"])
def test_save_load_round_trip_gives_identical_actions(fixture_name, request, tmp_path):
    from lerobot.policies.factory import make_pre_post_processors

    dataset = load_dataset(request.getfixturevalue(fixture_name))
    policy, preprocessor, postprocessor = make_bcrl_policy(dataset)
    # move the buffers and log-std away from their defaults so that a missed load would show
    policy.log_std.data.fill_(-2.5)
    policy.save_pretrained(tmp_path)
    preprocessor.save_pretrained(tmp_path)
    postprocessor.save_pretrained(tmp_path)
    assert {"config.json", "model.safetensors", "policy_preprocessor.json"} <= {p.name for p in tmp_path.iterdir()}

    loaded = BCRLPolicy.from_pretrained(tmp_path)
    loaded_pre, loaded_post = make_pre_post_processors(loaded.config, pretrained_path=str(tmp_path))
    raw = whole_dataset_batch(dataset)
    expected = postprocessor(policy.select_action(preprocessor(dict(raw))))
    actual = loaded_post(loaded.select_action(loaded_pre(dict(raw))))
    assert torch.equal(expected, actual)
    for name in ("gripper_class_weights", "aux_pos_mean", "aux_pos_std", "log_std"):
        assert torch.equal(getattr(policy, name), getattr(loaded, name)), name


def test_overfits_a_tiny_lowdim_dataset(lowdim_dataset_root):
    torch.manual_seed(0)
    dataset = load_dataset(lowdim_dataset_root)
    policy, preprocessor, _ = make_bcrl_policy(dataset)
    batch = preprocessor(whole_dataset_batch(dataset))
    optimizer = torch.optim.AdamW(policy.parameters(), lr=2e-3)
    policy.train()
    first_loss = None
    for _ in range(400):
        loss, metrics = policy.forward(batch)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        first_loss = first_loss or loss.item()
    final_loss, metrics = policy.forward(batch)
    assert final_loss.item() <= first_loss / 10, (first_loss, metrics)
    assert metrics["gripper_accuracy"] == 1.0


def test_a_dataset_of_another_layout_trains_and_acts_without_anything_of_lift():
    """The policy reads features by name and shape: other state widths, no aux.* targets."""
    from lerobot.configs.types import FeatureType, PolicyFeature

    config = BCRLConfig(device="cpu", observation_mode="low_dim", aux_weight=0.0, require_aux_targets=False,
                        input_features={"observation.state": PolicyFeature(FeatureType.STATE, (5,)),
                                        "observation.environment_state": PolicyFeature(FeatureType.ENV, (4,))},
                        output_features={"action": PolicyFeature(FeatureType.ACTION, (8,))})
    policy = BCRLPolicy(config)
    torch.manual_seed(0)
    batch = {"observation.state": torch.randn(6, 5), "observation.environment_state": torch.randn(6, 4),
             "action": torch.cat([torch.randn(6, 3) * 0.01, torch.tensor([[0.0, 0.0, 0.0, 1.0]] * 6),
                                  torch.tensor([[1.0], [-1.0]] * 3)], dim=-1)}
    loss, metrics = policy.forward(batch)
    loss.backward()
    assert torch.isfinite(loss) and "bc_aux_eef_mse" not in metrics
    assert_valid_actions(policy.select_action(batch))
