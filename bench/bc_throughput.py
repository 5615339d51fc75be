"""BC training throughput of the `bcrl` policy: data pipeline + step vs the model step alone, on CPU or a GPU.

Prints one JSON line per video backend, each with the model step alone on the same batches (the baseline). Example:
python bench/bc_throughput.py --root=/tmp/dev_img --batch_size=64 --steps=5 --video_backends=torchcodec,bcrl_frame_cache
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time

import numpy as np
import torch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--root", required=True, help="a bcrl-record dataset")
    parser.add_argument("--batch_size", type=int, default=64)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--latency_calls", type=int, default=50)
    parser.add_argument("--items", type=int, default=300, help="dataset items timed one by one in this process")
    parser.add_argument("--num_workers", type=int, default=1, help="DataLoader workers decoding beside the step")
    parser.add_argument("--device", default="cpu", help="where the model trains: cpu or cuda")
    parser.add_argument("--video_backends", default="torchcodec,bcrl_frame_cache",
                        help="comma-separated LeRobotDataset video backends to measure, one line each")
    args = parser.parse_args()
    for backend in args.video_backends.split(","):
        print(json.dumps(measure(args, backend)), flush=True)


def measure(args, video_backend: str) -> dict:
    from lerobot.configs.train import TrainPipelineConfig
    from lerobot.datasets.lerobot_dataset import LeRobotDataset
    from lerobot.policies.factory import make_policy, make_pre_post_processors

    from lerobot_bcrl.policies.bcrl.configuration_bcrl import BCRLConfig  # importing lerobot_bcrl: the frame cache too

    torch.manual_seed(0)
    dataset = LeRobotDataset("local/bench", root=args.root, video_backend=video_backend)
    cfg = BCRLConfig(device=args.device, push_to_hub=False)
    on_gpu = args.device.startswith("cuda")

    def now() -> float:  # CUDA runs asynchronously: wait for the queued work, so that a timer reads finished work
        if on_gpu:
            torch.cuda.synchronize()
        return time.perf_counter()

    policy = make_policy(cfg, ds_meta=dataset.meta)
    preprocessor, _ = make_pre_post_processors(cfg, dataset_stats=dataset.meta.stats)
    optimizer = cfg.get_optimizer_preset().build(policy.get_optim_params())
    # The loader lerobot-train builds: its default worker options (spawned workers, which also keep one backend's
    # decoded state from the next; persistent across epochs: a small dataset would otherwise restart its workers,
    # each decoding its files again, every few batches; its prefetch depth), pinned batches on a GPU.
    train_defaults = {f.name: f.default for f in dataclasses.fields(TrainPipelineConfig)}
    workers = {} if args.num_workers == 0 else {
        "multiprocessing_context": train_defaults["dataloader_multiprocessing_context"],
        "persistent_workers": train_defaults["persistent_workers"],
        "prefetch_factor": train_defaults["prefetch_factor"],
    }
    loader = torch.utils.data.DataLoader(dataset, batch_size=args.batch_size, shuffle=True, drop_last=True,
                                         num_workers=args.num_workers, pin_memory=on_gpu, **workers)

    def train_step(batch):
        loss, _ = policy.forward(batch)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()

    policy.train()
    batches = []
    iterator = iter(loader)
    for _ in range(max(1, args.num_workers)):  # every worker started, its first file decoded, outside the timing
        next(iterator)
    start = now()
    for _ in range(args.steps):
        try:
            raw = next(iterator)
        except StopIteration:
            iterator = iter(loader)
            raw = next(iterator)
        batch = preprocessor(raw)
        train_step(batch)
        batches.append(batch)
    pipeline_s = now() - start

    start = now()
    for batch in batches:
        train_step(batch)
    model_s = now() - start

    single = {k: v[:1] if isinstance(v, torch.Tensor) else v for k, v in batches[0].items()}
    latencies = []
    for _ in range(args.latency_calls):
        start = now()
        policy.select_action(single)
        latencies.append(now() - start)

    # One sample's cost in this process (what each DataLoader worker pays per sample), after the loader: LeRobot
    # warns against decoding in the main process before workers start. The first item, outside the timing, opens
    # the decoder (and, for the frame cache, decodes the whole file): the figure is the steady state.
    item_indices = torch.randperm(len(dataset))[: args.items].tolist()
    dataset[item_indices[0]]
    start = time.perf_counter()
    for index in item_indices:
        dataset[index]
    item_ms = 1000 * (time.perf_counter() - start) / len(item_indices)

    samples = args.steps * args.batch_size
    return {
        "video_backend": video_backend if dataset.meta.video_keys else None,
        "mode": "pixels" if cfg.uses_images else "low_dim",
        "batch_size": args.batch_size,
        "dataloader_workers": args.num_workers,
        "device": args.device,
        "torch_threads": torch.get_num_threads(),
        "pipeline_samples_per_s": samples / pipeline_s,
        "model_step_samples_per_s": samples / model_s,
        "model_busy_fraction": model_s / pipeline_s,  # target >= 0.9
        "dataset_item_ms": item_ms,  # steady state: the first item's decoding excluded
        "model_step_ms_per_sample": 1000 * model_s / samples,
        "select_action_p50_ms_batch1": 1000 * float(np.median(latencies)),
    }


if __name__ == "__main__":
    main()
