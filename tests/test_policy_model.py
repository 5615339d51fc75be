"""The `bcrl` policy on tiny recorded datasets: action format, PPO interface, save/load, overfitting."""

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

from lerobot_bcrl.policies.bcrl.configuration_bcrl import BCRLConfig
from lerobot_bcrl.policies.bcrl.modeling_bcrl import BCRLPolicy


def assert_valid_actions(actions: torch.Tensor):
    assert actions.shape[-1] == 8
    assert torch.allclose(actions[:, 3:7].norm(dim=-1), torch.ones(len(actions)), atol=1e-5)
    assert (actions[:, 6] >= 0).all()
    assert set(actions[:, 7].tolist()) <= {-1.0, 1.0}
    assert (actions[:, :3].norm(dim=-1) <= 0.05 + 1e-6).all()


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
    torch.manual_seed(0)
    sampled = postprocessor(policy.select_action(batch, sample=True))
    assert_valid_actions(sampled)
    assert not torch.allclose(sampled[:, :3], actions[:, :3])


def test_ppo_interface_log_prob_matches_between_sample_and_evaluate(lowdim_dataset_root):
    dataset = load_dataset(lowdim_dataset_root)
    policy, preprocessor, _ = make_bcrl_policy(dataset)
    batch = preprocessor(whole_dataset_batch(dataset))
    actions, log_prob, value = policy.sample_actions(batch)
    assert_valid_actions(actions)
    new_log_prob, entropy, new_value = policy.evaluate_actions(batch, actions)
    assert log_prob.shape == entropy.shape == value.shape == (len(dataset),)
    assert torch.allclose(log_prob, new_log_prob)
    assert torch.allclose(value, new_value)
    # gradients reach the learned log-std and the value head
    (-(new_log_prob.mean()) - entropy.mean() + new_value.pow(2).mean()).backward()
    assert policy.log_std.grad is not None and policy.model.value_head.weight.grad is not None


@pytest.mark.parametrize("fixture_name", ["lowdim_dataset_root", "image_dataset_root"])
def test_separate_critic_keeps_the_value_loss_off_the_actor(fixture_name, request):
    dataset = load_dataset(request.getfixturevalue(fixture_name))
    policy, preprocessor, _ = make_bcrl_policy(dataset, critic_hidden_dims=(32, 32))
    assert policy.model.value_head is None
    batch = preprocessor(whole_dataset_batch(dataset))
    _, _, value = policy.evaluate_actions(batch, policy.sample_actions(batch)[0])
    assert value.shape == (len(dataset),)
    value.pow(2).mean().backward()
    grads = {name: p.grad for name, p in policy.named_parameters()}
    critic = [name for name in grads if name.startswith("model.critic.")]
    assert critic and all(grads[name] is not None and grads[name].abs().sum() > 0 for name in critic)
    actor = [name for name in grads if name not in critic]
    assert any("keypoint_encoder" in name for name in actor) == (fixture_name == "image_dataset_root")
    assert all(grads[name] is None or not grads[name].any() for name in actor), "value loss reached the actor"


def test_bc_checkpoint_loads_with_a_fresh_separate_critic(lowdim_dataset_root, tmp_path):
    from lerobot.configs.policies import PreTrainedConfig
    from lerobot.policies.factory import make_policy

    dataset = load_dataset(lowdim_dataset_root)
    policy, preprocessor, _ = make_bcrl_policy(dataset)
    policy.save_pretrained(tmp_path)
    # what `bcrl-finetune --policy.path=<BC> --policy.critic_hidden_dims=[64]` does
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


@pytest.mark.parametrize("signed", [False, True])
def test_cube_yaw_features_are_the_turn_to_the_nearest_face_and_survive_save_load(lowdim_dataset_root, tmp_path, signed):
    import numpy as np
    from lerobot.policies.factory import make_pre_post_processors

    from lerobot_bcrl import geometry
    from lerobot_bcrl.features import CUBE_YAW_KEY, ENV_STATE_CUBE_QUAT, ENV_STATE_KEY, STATE_EEF_QUAT, STATE_KEY

    dataset = load_dataset(lowdim_dataset_root)
    policy, preprocessor, postprocessor = make_bcrl_policy(dataset, cube_yaw_features=True, cube_yaw_signed=signed)
    raw = whole_dataset_batch(dataset)
    batch = preprocessor(dict(raw))
    expected = np.array([geometry.cube_yaw_error(s[STATE_EEF_QUAT].numpy(), e[ENV_STATE_CUBE_QUAT].numpy())
                         for s, e in zip(raw[STATE_KEY], raw[ENV_STATE_KEY])])
    columns = [np.sin(4 * expected), np.cos(4 * expected)] + ([expected / (np.pi / 4)] if signed else [])
    np.testing.assert_allclose(batch[CUBE_YAW_KEY].numpy(), np.stack(columns, -1), atol=1e-4)
    assert not torch.allclose(batch[ENV_STATE_KEY], raw[ENV_STATE_KEY])  # the normalizer still ran after it
    loss, _ = policy.forward(dict(batch))
    assert torch.isfinite(loss)
    for part in (policy, preprocessor, postprocessor):
        part.save_pretrained(tmp_path)
    loaded = BCRLPolicy.from_pretrained(tmp_path)
    assert loaded.config.cube_yaw_features and loaded.config.cube_yaw_signed == signed
    loaded_pre, _ = make_pre_post_processors(loaded.config, pretrained_path=str(tmp_path))
    assert torch.equal(policy.select_action(preprocessor(dict(raw))), loaded.select_action(loaded_pre(dict(raw))))
    with pytest.raises(KeyError):  # without the step the policy must not silently run on missing features
        policy.select_action(make_bcrl_policy(dataset)[1](dict(raw)))


def test_signed_cube_yaw_flips_at_45_degrees_where_sin_cos_cannot_tell():
    import math

    from lerobot_bcrl import geometry
    from lerobot_bcrl.features import CUBE_YAW_KEY, ENV_STATE_CUBE_QUAT, ENV_STATE_KEY, STATE_EEF_QUAT, STATE_KEY
    from lerobot_bcrl.policies.bcrl.processor_bcrl import CubeYawFeaturesStep

    state, env_state = torch.zeros(2, 16), torch.zeros(2, 10)
    state[:, STATE_EEF_QUAT] = torch.tensor(geometry.IDENTITY_QUAT_XYZW, dtype=torch.float32)  # eef yaw 0
    for row, cube_yaw_deg in enumerate((44.0, 46.0)):  # -44 degrees to the nearest face for the second
        cube = geometry.rotvec_to_quat([0.0, 0.0, math.radians(cube_yaw_deg)])
        env_state[row, ENV_STATE_CUBE_QUAT] = torch.tensor(cube, dtype=torch.float32)
    features = CubeYawFeaturesStep(signed=True).observation({STATE_KEY: state, ENV_STATE_KEY: env_state})[CUBE_YAW_KEY]
    torch.testing.assert_close(features[:, 2], torch.tensor([44 / 45, -44 / 45]), atol=1e-5, rtol=0)
    assert (features[0, :2] - features[1, :2]).norm() < 0.15  # (sin 4d, cos 4d) of 44 and -44 degrees: nearly alike
    with pytest.raises(ValueError, match="cube_yaw_features=true"):
        BCRLConfig(cube_yaw_signed=True)
