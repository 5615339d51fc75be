"""`video_backend=bcrl_frame_cache`: the same frames as LeRobot's own decoder, a clear error off the frame grid."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from lerobot.datasets.lerobot_dataset import LeRobotDataset
from lerobot.datasets.video_utils import FrameTimestampError

from lerobot_bcrl import frame_cache
from lerobot_bcrl.features import IMAGE_KEY


@pytest.fixture(scope="module")
def video_dataset_root(tmp_path_factory):
    from dataset_tools.record import RecordConfig, record

    root = tmp_path_factory.mktemp("video") / "two_episodes"
    # two episodes in one MP4 file (LeRobotDataset v3 concatenates them): the second starts at an offset
    return record(RecordConfig(repo_id="local/two_episodes", root=root, n_episodes=2, episode_length=12, sigma=0.1,
                               images=True, video=True))


def test_cached_frames_equal_lerobots_decoder_in_every_episode(video_dataset_root):
    lerobot_decoded = LeRobotDataset("local/two_episodes", root=video_dataset_root, video_backend="torchcodec")
    cached = LeRobotDataset("local/two_episodes", root=video_dataset_root, video_backend=frame_cache.BACKEND)
    assert len(list((video_dataset_root / "videos").rglob("*.mp4"))) == 1 and cached.num_episodes == 2
    for index in range(len(cached)):  # the second episode's frames come from its offset in the shared file
        frame, reference = cached[index][IMAGE_KEY], lerobot_decoded[index][IMAGE_KEY]
        assert frame.dtype == reference.dtype == torch.float32 and frame.shape == reference.shape
        assert torch.equal(frame, reference), f"frame {index} differs"
    # the frames of different steps differ, so the comparison above could fail
    assert not torch.equal(cached[0][IMAGE_KEY], cached[11][IMAGE_KEY])


def test_spawned_dataloader_workers_decode_with_the_cache(video_dataset_root):
    # lerobot-train's workers are spawned (fresh interpreters that load no plugin) and persistent
    reference = LeRobotDataset("local/two_episodes", root=video_dataset_root, video_backend="torchcodec")
    cached = LeRobotDataset("local/two_episodes", root=video_dataset_root, video_backend=frame_cache.BACKEND)
    loader = torch.utils.data.DataLoader(cached, batch_size=len(cached), num_workers=1,
                                         multiprocessing_context="spawn")
    frames = next(iter(loader))[IMAGE_KEY]
    assert torch.equal(frames, torch.stack([reference[i][IMAGE_KEY] for i in range(len(reference))]))


def test_a_worker_that_builds_the_reader_itself_decodes_with_the_cache(video_dataset_root):
    # a dataset whose reader was not built yet (LeRobotDataset builds it on first access): the spawned worker builds
    # it from the dataset's own backend name, which must install the decoder when unpickled
    cached = LeRobotDataset("local/two_episodes", root=video_dataset_root, video_backend=frame_cache.BACKEND)
    expected = torch.stack([cached[i][IMAGE_KEY] for i in range(len(cached))])
    cached.reader = None
    loader = torch.utils.data.DataLoader(cached, batch_size=len(cached), num_workers=1,
                                         multiprocessing_context="spawn")
    assert torch.equal(next(iter(loader))[IMAGE_KEY], expected)


def test_pyav_fallback_decodes_the_frames_lerobots_pyav_decoder_gives(video_dataset_root):
    from lerobot.datasets.video_utils import decode_video_frames_pyav

    video = next((video_dataset_root / "videos").rglob("*.mp4"))
    frames, pts = frame_cache._decoded_with_pyav(str(video))
    assert len(frames) == 24 and bool((pts.diff() > 0).all())  # two episodes of 12 frames, in time order
    reference = decode_video_frames_pyav(video, pts.tolist(), 1e-4, return_uint8=True)
    assert frames.dtype == torch.uint8 and torch.equal(frames, reference)


def test_clear_forgets_the_decoded_videos(video_dataset_root):
    video = next((video_dataset_root / "videos").rglob("*.mp4"))
    frame_cache.decode_cached(video, [0.0], 1e-4)
    assert frame_cache._decoded.cache_info().currsize >= 1
    frame_cache.clear()
    assert frame_cache._decoded.cache_info().currsize == 0


def test_a_timestamp_off_the_frame_grid_names_the_file(video_dataset_root):
    video = next((video_dataset_root / "videos").rglob("*.mp4"))
    half_frame_s = 0.5 / LeRobotDataset("local/two_episodes", root=video_dataset_root).fps
    assert frame_cache.decode_cached(video, [0.0, 2 * half_frame_s], 1e-4, return_uint8=True).dtype == torch.uint8
    with pytest.raises(FrameTimestampError, match=video.name):
        frame_cache.decode_cached(video, [half_frame_s], 1e-4)


def test_episode_metadata_is_read_once_per_episode_and_camera(video_dataset_root, monkeypatch):
    # LeRobot reads an episode's metadata row for every item; the cache keeps where each episode's frames are
    cached = LeRobotDataset("local/two_episodes", root=video_dataset_root, video_backend=frame_cache.BACKEND)
    reference = [cached[i][IMAGE_KEY] for i in range(len(cached))]
    cached = LeRobotDataset("local/two_episodes", root=video_dataset_root, video_backend=frame_cache.BACKEND)
    lookups = []
    lookup = type(cached.meta).get_video_file_path
    monkeypatch.setattr(type(cached.meta), "get_video_file_path",
                        lambda meta, ep_index, vid_key: lookups.append(ep_index) or lookup(meta, ep_index, vid_key))
    for _ in range(2):
        frames = [cached[i][IMAGE_KEY] for i in range(len(cached))]
    assert sorted(lookups) == [0, 1]
    assert all(torch.equal(frame, expected) for frame, expected in zip(frames, reference, strict=True))


@pytest.fixture(scope="module")
def rgb_and_depth_dataset_root(tmp_path_factory):
    # a camera and a depth camera (LeRobot's own depth encoding: 12-bit codes of millimetres); depth 300 + 100 t mm
    root = tmp_path_factory.mktemp("depth") / "rgb_and_depth"
    features = {
        "observation.images.rgb": {"dtype": "video", "shape": (64, 64, 3), "names": ["height", "width", "channels"]},
        "observation.images.depth": {"dtype": "video", "shape": (64, 64, 1), "names": ["height", "width", "channels"],
                                     "info": {"is_depth_map": True}},
        "action": {"dtype": "float32", "shape": (2,), "names": None},
    }
    dataset = LeRobotDataset.create("local/rgb_and_depth", fps=10, root=root, features=features, use_videos=True)
    rng = np.random.default_rng(0)
    for _ in range(2):
        for t in range(6):
            dataset.add_frame({"observation.images.rgb": rng.integers(0, 256, (64, 64, 3), dtype=np.uint8),
                               "observation.images.depth": np.full((64, 64, 1), 300 + 100 * t, dtype=np.uint16),
                               "action": np.zeros(2, dtype=np.float32), "task": "lift"})
        dataset.save_episode()
    dataset.finalize()
    return root


def test_an_episode_with_a_depth_camera_decodes_each_rgb_frame_once(rgb_and_depth_dataset_root, monkeypatch):
    # the depth camera goes to LeRobot's decoder; the RGB camera is served by the cache, once per item
    reference = LeRobotDataset("local/rgb_and_depth", root=rgb_and_depth_dataset_root, video_backend="pyav")
    cached = LeRobotDataset("local/rgb_and_depth", root=rgb_and_depth_dataset_root, video_backend=frame_cache.BACKEND)
    assert cached.meta.depth_keys == ["observation.images.depth"]
    decoded_paths = []
    decode = frame_cache.decode_cached
    monkeypatch.setattr(frame_cache, "decode_cached",
                        lambda path, *args, **kwargs: decoded_paths.append(str(path)) or decode(path, *args, **kwargs))
    for index in range(len(cached)):
        item, expected = cached[index], reference[index]
        for key in ("observation.images.rgb", "observation.images.depth"):
            assert torch.equal(item[key], expected[key]), f"{key} of frame {index} differs"
    assert len(decoded_paths) == len(cached) and all("observation.images.rgb" in path for path in decoded_paths)
    # the depth frames are the recorded millimetres (LeRobot's 12-bit codes round them), so they could differ
    depth_mm = [float(cached[index]["observation.images.depth"].mean()) for index in (0, 5)]
    assert depth_mm[0] == pytest.approx(300, rel=0.05) and depth_mm[1] == pytest.approx(800, rel=0.05)
