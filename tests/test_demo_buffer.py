"""The BC term's demonstrations in memory: camera frames kept as uint8, read chunk by chunk, served as the dataset
serves them."""

from __future__ import annotations

import pytest
import torch
from policy_fixtures import load_dataset, record_tiny_dataset

from lerobot_bcrl.features import IMAGES_PREFIX
from lerobot_bcrl.rl.demo_buffer import DemoBuffer


@pytest.fixture(scope="module")
def image_dataset_of_two_chunks(tmp_path_factory):
    """300 camera frames: more than one of the buffer's 256-frame reading chunks."""
    return record_tiny_dataset(tmp_path_factory.mktemp("data") / "images_300", True, 2, 150)


def test_demo_buffer_holds_camera_frames_as_uint8_and_serves_each_frame_as_the_dataset_does(
        image_dataset_of_two_chunks):
    dataset = load_dataset(image_dataset_of_two_chunks)
    buffer = DemoBuffer(dataset, batch_size=64, seed=0, preprocessor=lambda batch: batch)
    image_keys = [key for key in buffer.frames if key.startswith(IMAGES_PREFIX)]
    assert image_keys and all(buffer.frames[key].dtype == torch.uint8 for key in image_keys)
    assert buffer.n_frames == len(dataset) == 300
    assert buffer.frames["index"].tolist() == list(range(300))  # the chunks joined in order

    batch = next(buffer)
    assert sorted(set(batch["index"].tolist())) != sorted(range(64))  # sampled, not the first frames
    for row, index in enumerate(batch["index"].tolist()):
        item = dataset[index]
        for key in image_keys:  # one uint8 step of rounding at most
            assert (batch[key][row] - item[key]).abs().max() <= 0.5 / 255 + 1e-6
        assert torch.equal(batch["observation.state"][row], item["observation.state"])
        assert torch.equal(batch["action"][row], item["action"])
