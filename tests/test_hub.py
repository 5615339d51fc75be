"""bcrl-hub against a real HTTP hub-compatible server on 127.0.0.1 with the real huggingface_hub client."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from dataset_tools.local_hub import LocalHub
from policy_fixtures import load_dataset, lowdim_dataset_root, record_tiny_dataset, save_untrained_checkpoint  # noqa: F401

TOKEN = "hf_test_token"
BIN = Path(sys.executable).parent


@pytest.fixture(scope="module")
def hub(tmp_path_factory):
    with LocalHub(tmp_path_factory.mktemp("hub"), tokens={TOKEN}) as server:
        yield server


@pytest.fixture(scope="module")
def video_dataset(tmp_path_factory):
    from dataset_tools.record import RecordConfig, record

    root = tmp_path_factory.mktemp("src") / "lift"
    record(RecordConfig(repo_id="local/lift", root=root, n_episodes=2, episode_length=20, image_size=64, sigma=0.1))
    return root


@pytest.fixture
def api(hub, monkeypatch):
    """The real client, in this process, talking to the local hub (tests run with HF_HUB_OFFLINE=1)."""
    from huggingface_hub import HfApi, constants

    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", False)
    monkeypatch.setattr(constants, "HF_HUB_DISABLE_XET", True)
    return HfApi(endpoint=hub.url, token=TOKEN)


def run_hub(hub, *args, token=TOKEN, check=True):
    env = {**os.environ, "HF_ENDPOINT": hub.url, "HF_HUB_OFFLINE": "1"}  # bcrl-hub must override offline mode
    env.pop("HF_HUB_DISABLE_XET", None)
    if token:
        env["HF_TOKEN"] = token
    else:
        env.pop("HF_TOKEN", None)
    result = subprocess.run([str(BIN / "bcrl-hub"), *args], capture_output=True, text=True, env=env)
    if check and result.returncode != 0:
        raise AssertionError(f"bcrl-hub {' '.join(args)} failed:\n{result.stdout}\n{result.stderr}")
    return result


def dataset_files(root: Path) -> dict[str, bytes]:
    return {
        str(p.relative_to(root)): p.read_bytes()
        for p in sorted(root.rglob("*"))
        if p.is_file() and not str(p.relative_to(root)).startswith((".cache", "images"))
    }


@pytest.mark.slow
def test_dataset_push_pull_round_trip(hub, video_dataset, tmp_path):
    run_hub(hub, "push", "--kind=dataset", "--repo_id=lab/lift", f"--root={video_dataset}", "--private=true")
    uploads = [path for method, path, _ in hub.state.log if method == "PUT" and path.startswith("/lfs-upload/")]
    assert len(uploads) >= 3  # parquet data, episode metadata and the mp4 went through the LFS path

    pulled = tmp_path / "pulled"
    out = run_hub(hub, "pull", "--kind=dataset", "--repo_id=lab/lift", f"--root={pulled}").stdout
    assert str(pulled) in out
    original, copy = dataset_files(video_dataset), dataset_files(pulled)
    assert set(original) <= set(copy) and "README.md" in copy
    for name, content in original.items():
        assert copy[name] == content, name  # byte for byte
    assert not (pulled / ".cache").exists()

    card = (pulled / "README.md").read_text()
    assert "noise sigma = 0.1" in card and "20 fps" in card and "dx, dy, dz" in card and "bcrl-record" in card

    a, b = load_dataset(video_dataset), load_dataset(pulled)
    assert b.num_episodes == 2 and b.num_frames == a.num_frames
    for i in (0, 27):
        for key in ("observation.state", "action", "observation.images.agentview"):
            torch.testing.assert_close(a[i][key], b[i][key])


@pytest.mark.slow
def test_upstream_lerobot_dataset_loads_from_the_hub(hub, video_dataset, tmp_path):
    run_hub(hub, "push", "--kind=dataset", "--repo_id=lab/public_lift", f"--root={video_dataset}")
    from dataset_tools.hub import configure_hub
    from lerobot.datasets.lerobot_dataset import LeRobotDataset

    os.environ["HF_ENDPOINT"] = hub.url
    try:
        configure_hub()
        ds = LeRobotDataset("lab/public_lift", root=tmp_path / "lerobot_cache")  # downloads: nothing local yet
        assert ds.num_episodes == 2
        torch.testing.assert_close(ds[5]["action"], load_dataset(video_dataset)[5]["action"])
    finally:
        os.environ.pop("HF_ENDPOINT")


def test_private_repo_needs_the_token(hub, api, tmp_path):
    api.create_repo("lab/secret", repo_type="dataset", private=True)
    result = run_hub(hub, "pull", "--kind=dataset", "--repo_id=lab/secret", f"--root={tmp_path / 'x'}", "--revision=main", token=None, check=False)
    assert result.returncode == 1 and "bcrl-hub: error" in result.stderr
    assert not (tmp_path / "x").exists()


@pytest.mark.slow
def test_pull_pinned_to_a_revision(hub, api, tmp_path):
    v1 = record_tiny_dataset(tmp_path / "v1", images=False, n_episodes=1, episode_length=10)
    run_hub(hub, "push", "--kind=dataset", "--repo_id=lab/versions", f"--root={v1}")
    first_sha = api.repo_info("lab/versions", repo_type="dataset").sha
    v2 = record_tiny_dataset(tmp_path / "v2", images=False, n_episodes=2, episode_length=10)
    run_hub(hub, "push", "--kind=dataset", "--repo_id=lab/versions", f"--root={v2}")

    run_hub(hub, "pull", "--kind=dataset", "--repo_id=lab/versions", f"--root={tmp_path / 'old'}", f"--revision={first_sha}")
    run_hub(hub, "pull", "--kind=dataset", "--repo_id=lab/versions", f"--root={tmp_path / 'new'}")
    assert load_dataset(tmp_path / "old").num_episodes == 1
    assert load_dataset(tmp_path / "new").num_episodes == 2


@pytest.mark.slow
def test_interrupted_and_corrupted_pulls_fail_loudly_and_resume(hub, tmp_path):
    root = record_tiny_dataset(tmp_path / "src", images=False, n_episodes=1, episode_length=10)
    run_hub(hub, "push", "--kind=dataset", "--repo_id=lab/faulty", f"--root={root}")
    data_file = "data/chunk-000/file-000.parquet"
    dest = tmp_path / "dest"
    pull_args = ("pull", "--kind=dataset", "--repo_id=lab/faulty", f"--root={dest}")

    hub.state.faults.truncate_always.add(data_file)
    failed = run_hub(hub, *pull_args, check=False)
    assert failed.returncode == 1 and "run the same command again to resume" in failed.stderr
    assert not dest.exists()  # no half dataset where the user looks
    staging = tmp_path / ".dest.pulling"
    completed = {str(p.relative_to(staging)) for p in staging.rglob("*") if p.is_file() and ".cache" not in p.parts}
    assert completed and data_file not in completed
    hub.state.faults.truncate_always.clear()
    hub.state.log.clear()
    run_hub(hub, *pull_args)
    fetched = {p.split("/resolve/", 1)[1].split("/", 1)[1] for m, p, _ in hub.state.log if m == "GET" and "/resolve/" in p}
    assert data_file in fetched and not (completed & fetched)  # the retry fetched only what was missing
    assert dataset_files(dest)[data_file] == (root / data_file).read_bytes()

    hub.state.faults.corrupt.add("meta/info.json")
    dest2 = tmp_path / "dest2"
    failed = run_hub(hub, "pull", "--kind=dataset", "--repo_id=lab/faulty", f"--root={dest2}", check=False)
    assert failed.returncode == 1 and "meta/info.json: corrupted download" in failed.stderr
    assert not dest2.exists()
    hub.state.faults.corrupt.clear()
    run_hub(hub, "pull", "--kind=dataset", "--repo_id=lab/faulty", f"--root={dest2}")
    assert json.loads((dest2 / "meta/info.json").read_text())["total_episodes"] == 1


@pytest.mark.slow
def test_policy_push_pull_and_safety_checks(hub, api, lowdim_dataset_root, tmp_path):
    from lerobot.policies.factory import get_policy_class

    dataset = load_dataset(lowdim_dataset_root)
    checkpoint = tmp_path / "pretrained_model"
    policy, preprocessor, _ = save_untrained_checkpoint(lowdim_dataset_root, checkpoint)
    run_hub(hub, "push", "--kind=policy", "--repo_id=lab/bcrl", f"--root={checkpoint}", "--private=true")
    pulled = tmp_path / "pulled_policy"
    run_hub(hub, "pull", "--kind=policy", "--repo_id=lab/bcrl", f"--root={pulled}")
    for f in checkpoint.iterdir():
        assert (pulled / f.name).read_bytes() == f.read_bytes(), f.name
    assert "lerobot-eval --policy.path=lab/bcrl" in (pulled / "README.md").read_text()
    restored = get_policy_class("bcrl").from_pretrained(pulled)
    batch = preprocessor({k: v.unsqueeze(0) for k, v in dataset[3].items() if k.startswith("observation.")})
    policy.eval()
    torch.testing.assert_close(policy.select_action(batch), restored.select_action(batch))

    # a checkpoint whose config this version cannot interpret is refused, not run
    config = json.loads((checkpoint / "config.json").read_text())
    config["mystery_option"] = 3
    (checkpoint / "config.json").write_text(json.dumps(config))
    run_hub(hub, "push", "--kind=policy", "--repo_id=lab/bcrl", f"--root={checkpoint}", check=False)  # push refuses too
    api.upload_file(
        path_or_fileobj=(checkpoint / "config.json").read_bytes(), path_in_repo="config.json", repo_id="lab/bcrl"
    )
    refused = run_hub(hub, "pull", "--kind=policy", "--repo_id=lab/bcrl", f"--root={tmp_path / 'bad'}", check=False)
    assert refused.returncode == 1 and "unknown config keys ['mystery_option']" in refused.stderr
    assert not (tmp_path / "bad").exists()

    (checkpoint / "config.json").write_text(json.dumps({k: v for k, v in config.items() if k != "mystery_option"}))
    (checkpoint / "extra.bin").write_bytes(b"\x80\x04pickle")
    refused = run_hub(hub, "push", "--kind=policy", "--repo_id=lab/bcrl", f"--root={checkpoint}", check=False)
    assert refused.returncode == 1 and "refusing pickle files ['extra.bin']" in refused.stderr


def test_bad_arguments_are_reported(hub):
    result = run_hub(hub, "push", "--kind=weights", "--repo_id=lab/x", "--root=/nonexistent", check=False)
    assert result.returncode == 1 and "--kind must be 'dataset' or 'policy'" in result.stderr
    result = run_hub(hub, "pull", "--repo_id=not-a-repo-id", check=False)
    assert result.returncode == 1 and "owner/name" in result.stderr
