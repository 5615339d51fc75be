"""BC+RL learner step of an image `bcrl` policy on the CPU: one PPO minibatch plus one demo batch, the joint loss
with `term_weighting="gradient_share"`, its backward pass and the optimiser step.

Prints one JSON line per variant, each measured on the same batches in the same process:
- `baseline`: the whole batch through the CNN at once, the two term norms over every parameter (two more backward
  passes through the CNN per minibatch);
- `bcrl`: what bcrl-finetune runs: batches above `CPU_CHUNK_FRAMES` through the CNN in checkpointed chunks, the term
  norms over the layers after the CNN (`BCRLAgent.term_norm_parameters`);
- `bcrl` again with `--threads` torch threads (bcrl-finetune's `--learner_threads`), when more than 1.
Then one line per batch size for the image encoder alone (forward and backward of a batch of random frames), as one
batch and in checkpointed chunks smaller than the batch (32, 64): what chose `CPU_CHUNK_FRAMES`.
Example: python bench/learner_throughput.py --root=outputs/results/bench_img --steps=5
"""

import argparse
import json
import time
from unittest import mock

import torch

from lerobot_bcrl.policies.bcrl import modeling_bcrl


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--root", required=True, help="a bcrl-record dataset with a camera")
    parser.add_argument("--minibatch_size", type=int, default=256, help="PPO minibatch and demo batch, as the config")
    parser.add_argument("--steps", type=int, default=5, help="timed learner steps per variant (after one untimed)")
    parser.add_argument("--threads", type=int, default=1, help="torch threads of a last `bcrl` variant (if > 1)")
    args = parser.parse_args()

    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    from lerobot_bcrl.policies.bcrl.configuration_bcrl import BCRLConfig
    from lerobot_bcrl.rl.agent import BCRLAgent
    from lerobot_bcrl.rl.demo_buffer import DemoBuffer
    from lerobot_bcrl.rl.ppo import PPOConfig, bcrl_loss

    torch.set_num_threads(1)  # as bcrl-finetune's learner
    torch.manual_seed(0)
    dataset = LeRobotDataset("local/bench", root=args.root, video_backend="bcrl_frame_cache")
    # configs/bc_lift_images.json's policy (make_policy refuses a dataset without a camera)
    cfg = BCRLConfig(device="cpu", observation_mode="pixels", critic_hidden_dims=(256, 256), aux_weight=0.1)
    policy = make_policy(cfg, ds_meta=dataset.meta)
    preprocessor, _ = make_pre_post_processors(cfg, dataset_stats=dataset.meta.stats)
    agent = BCRLAgent(policy, preprocessor)
    demo_batches = DemoBuffer(dataset, args.minibatch_size, 0, preprocessor)
    optimizer = torch.optim.Adam(policy.parameters(), lr=1e-5, eps=1e-5)
    ppo_cfg = PPOConfig(term_weighting="gradient_share")

    minibatches = []  # PPO minibatches: demo frames as observations, the policy's own samples as actions
    for _ in range(args.steps + 1):
        obs = {k: v for k, v in next(demo_batches).items() if k.startswith("observation.")}
        with torch.no_grad():
            actions, log_probs, _ = agent.sample(obs)
        n = len(actions)
        minibatches.append({"obs": obs, "actions": actions, "log_probs": log_probs + 0.1,
                            "advantages": torch.randn(n), "returns": torch.randn(n)})
    demos = [next(demo_batches) for _ in minibatches]
    every_parameter = [p for p in policy.parameters() if p.requires_grad]

    def learner_step(minibatch, demo):
        loss, _ = bcrl_loss(agent, minibatch, demo, 0.5, ppo_cfg, policy.forward)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    def seconds_per_step() -> float:
        policy.train()
        learner_step(minibatches[0], demos[0])  # allocator and thread pools warm, outside the timing
        start = time.perf_counter()
        for minibatch, demo in zip(minibatches[1:], demos[1:]):
            learner_step(minibatch, demo)
        return (time.perf_counter() - start) / args.steps

    with mock.patch.object(modeling_bcrl, "CPU_CHUNK_FRAMES", 10**9), \
            mock.patch.object(agent, "term_norm_parameters", lambda: every_parameter):
        baseline_s = seconds_per_step()
    variants = [("baseline", 1, baseline_s), ("bcrl", 1, seconds_per_step())]
    if args.threads > 1:
        torch.set_num_threads(args.threads)
        variants.append(("bcrl", args.threads, seconds_per_step()))
        torch.set_num_threads(1)
    for variant, threads, seconds in variants:
        print(json.dumps({
            "variant": variant,
            "minibatch_size": args.minibatch_size,
            "image_shape": list(cfg.image_features[cfg.image_key].shape),
            "torch_threads": threads,
            "learner_step_s": seconds,
            "ms_per_ppo_sample": 1000 * seconds / args.minibatch_size,  # its demo sample included
            "speedup_over_baseline": baseline_s / seconds,
        }), flush=True)
    for batch_size in (64, 256):
        print(json.dumps(encoder_ms_per_frame(policy.model.keypoint_encoder, batch_size, args.steps)), flush=True)


def encoder_ms_per_frame(encoder, batch_size: int, repeats: int) -> dict:
    """Milliseconds per frame of the encoder's forward and backward, one batch against chunks smaller than the batch
    (its `CPU_CHUNK_FRAMES` path with the chunk size patched)."""
    images = torch.rand(batch_size, 3, 128, 128)
    result = {"variant": "encoder_forward_backward", "batch_size": batch_size, "torch_threads": torch.get_num_threads()}
    for name, chunk in [("one_batch", 10**9)] + [(f"chunks_of_{n}", n) for n in (32, 64) if n < batch_size]:
        with mock.patch.object(modeling_bcrl, "CPU_CHUNK_FRAMES", chunk):
            encoder(images).sum().backward()  # warm, outside the timing
            start = time.perf_counter()
            for _ in range(repeats):
                encoder(images).sum().backward()
        result[f"{name}_ms_per_frame"] = 1000 * (time.perf_counter() - start) / (repeats * batch_size)
    return result


if __name__ == "__main__":
    main()
