"""`--dataset.video_backend=bcrl_frame_cache`: LeRobotDataset's frames decoded once per video file and served from memory.

LeRobotDataset decodes every sample's frame from its MP4 (seek to the key frame, decode up to the frame): for a
128x128 camera that costs about as much as the `bcrl` model's whole training step on a CPU, so the model waits on the
data ([RESULTS](../docs/RESULTS.md#bc-training-throughput)). This backend decodes a whole video file the first time a
process asks for one of its frames (torchcodec, in order, no seeking; PyAV where torchcodec cannot load, e.g. without
FFmpeg's shared libraries), keeps the frames as contiguous uint8 (49 KB a 128x128 frame: about 1 GB per 20,000
frames, in each DataLoader worker that reads them) and answers each query by the nearest frame, within LeRobot's
timestamp tolerance as its own decoders check it. It also keeps, per episode and camera, the video file and the
episode's start in it, which LeRobot reads from the episode metadata twice for every sample. `clear()` lets the
decoded videos go once their frames are copied elsewhere (bcrl-finetune's demo buffer).

LeRobot picks its decoder by name inside `lerobot.datasets.dataset_reader`; `install()` wraps that function, and the
reader's per-sample video query, so that this name is understood and every other name goes to LeRobot's code
unchanged (one LeRobot version, checked like `policies/bcrl/aux_targets.py`). Importing `lerobot_bcrl` (as
lerobot-train's plugin loading does) installs it. lerobot-train's DataLoader workers are spawned, fresh interpreters
that unpickle the dataset without loading plugins: so a dataset, and a reader, built with this backend hold its name
as a `FrameCacheBackend`, a `str` whose unpickling imports this module, which installs the decoder in the worker
before its first frame (also when the worker builds the reader itself).
"""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import torch
from lerobot.datasets import dataset_reader, lerobot_dataset
from lerobot.datasets.video_utils import FrameTimestampError
from torch import Tensor

from lerobot_bcrl.policies.bcrl.aux_targets import require_lerobot_version

BACKEND = "bcrl_frame_cache"


class FrameCacheBackend(str):
    """The backend's name; pickled by reference to this module, so a spawned worker that unpickles it installs the
    decoder."""


@functools.lru_cache(maxsize=None)
def _decoded(video_path: str, mtime_ns: int) -> tuple[Tensor, Tensor]:
    """Every frame of a video file, (N, C, H, W) uint8, and its presentation time in seconds (N,), ascending."""
    try:  # torchcodec loads FFmpeg's shared libraries on import or on its first decoder
        from torchcodec.decoders import VideoDecoder

        decoder = VideoDecoder(video_path)
    except (ImportError, OSError, RuntimeError):
        return _decoded_with_pyav(video_path)
    batch = decoder.get_frames_in_range(0, len(decoder))
    # torchcodec's frames are a channels-last view: one frame copies several times faster from contiguous memory
    return batch.data.contiguous(), batch.pts_seconds.double()


def _decoded_with_pyav(video_path: str) -> tuple[Tensor, Tensor]:
    """`_decoded` with PyAV (LeRobot's other decoder, bundling its own FFmpeg): RGB frames in order."""
    import av

    frames, pts_s = [], []
    with av.open(video_path) as container:
        stream = container.streams.video[0]
        for frame in container.decode(stream):
            if frame.pts is None:
                continue
            frames.append(torch.from_numpy(frame.to_ndarray(format="rgb24")).permute(2, 0, 1))
            pts_s.append(float(frame.pts * stream.time_base))
    pts = torch.tensor(pts_s, dtype=torch.float64)
    order = pts.argsort()
    return torch.stack(frames)[order].contiguous(), pts[order]


def clear() -> None:
    """Forget every decoded video in this process (the next query decodes its file again)."""
    _decoded.cache_clear()


def decode_cached(video_path: Path | str, timestamps: list[float], tolerance_s: float,
                  return_uint8: bool = False) -> Tensor:
    """The frames nearest to `timestamps` (seconds in the file), float in [0, 1] (or uint8), like LeRobot's decoders."""
    path = Path(video_path)
    frames, pts = _decoded(str(path), path.stat().st_mtime_ns)
    pts_s = pts.numpy()  # numpy for the index arithmetic: on one or a few timestamps torch's per-call cost dominates
    query = np.asarray(timestamps, dtype=np.float64)
    after = np.searchsorted(pts_s, query).clip(1, len(pts_s) - 1)
    nearer_before = np.abs(query - pts_s[after - 1]) <= np.abs(pts_s[after] - query)
    index = np.where(nearer_before, after - 1, after)
    distance = np.abs(pts_s[index] - query)
    if (distance >= tolerance_s).any():
        worst = int(distance.argmax())
        raise FrameTimestampError(
            f"{path}: no frame within {tolerance_s} s of {timestamps[worst]:.6f} s (nearest at {pts_s[index[worst]]:.6f} s)"
        )
    selected = frames.index_select(0, torch.from_numpy(index))  # (an index tensor in [] copies ~30x slower here)
    return selected if return_uint8 else selected.float().div_(255.0)


def _episode_video(reader, ep_idx: int, vid_key: str) -> tuple[Path, float] | None:
    """Where an episode's frames of one camera are: its video file and its start in that file (seconds); None for a
    depth camera (left to LeRobot)."""
    if vid_key in reader._meta.depth_keys:
        return None
    from_timestamp_s = float(reader._meta.episodes[ep_idx][f"videos/{vid_key}/from_timestamp"])
    return reader.root / reader._meta.get_video_file_path(ep_idx, vid_key), from_timestamp_s


def install() -> None:
    """Let LeRobotDataset decode with `video_backend=bcrl_frame_cache` (idempotent)."""
    require_lerobot_version()
    lerobot_decode = dataset_reader.decode_video_frames
    if getattr(lerobot_decode, "bcrl_frame_cache", False):
        return
    reader_init = dataset_reader.DatasetReader.__init__
    dataset_init = lerobot_dataset.LeRobotDataset.__init__

    @functools.wraps(reader_init)
    def init_reader(self, *args, **kwargs):
        reader_init(self, *args, **kwargs)
        if self._video_backend == BACKEND:
            self._video_backend = FrameCacheBackend(BACKEND)

    @functools.wraps(dataset_init)
    def init_dataset(self, *args, **kwargs):
        dataset_init(self, *args, **kwargs)
        if self._video_backend == BACKEND:  # a reader the dataset builds later (in a worker) gets the name from here
            self._video_backend = FrameCacheBackend(BACKEND)

    @functools.wraps(lerobot_decode)
    def decode_video_frames(video_path, timestamps, tolerance_s, backend=None, return_uint8=False, is_depth=False):
        # reached through LeRobot's own query (below) when an episode has a depth camera: its RGB cameras come from
        # the cache, its depth goes to LeRobot, which decodes depth with PyAV whatever the backend's name
        if backend == BACKEND and not is_depth:
            return decode_cached(video_path, timestamps, tolerance_s, return_uint8=return_uint8)
        return lerobot_decode(video_path, timestamps, tolerance_s, backend, return_uint8=return_uint8, is_depth=is_depth)

    lerobot_query_videos = dataset_reader.DatasetReader._query_videos

    @functools.wraps(lerobot_query_videos)
    def query_videos(self, query_timestamps, ep_idx):
        # LeRobot reads the episode's metadata row twice per item (its start in the file, the file's path), the
        # largest part of an item's cost once decoding is gone: this backend keeps both per episode and camera.
        if self._video_backend != BACKEND:
            return lerobot_query_videos(self, query_timestamps, ep_idx)
        videos = self.__dict__.setdefault("bcrl_episode_videos", {})
        located = {}
        for vid_key in query_timestamps:
            if (ep_idx, vid_key) not in videos:
                videos[ep_idx, vid_key] = _episode_video(self, ep_idx, vid_key)
            located[vid_key] = videos[ep_idx, vid_key]
        if None in located.values():
            # a depth camera: LeRobot's own query, for its decoder and dequantisation; that query's calls for the
            # episode's RGB cameras reach the cache through `decode_video_frames` above
            return lerobot_query_videos(self, query_timestamps, ep_idx)
        return {
            vid_key: decode_cached(video_path, [from_timestamp_s + ts for ts in query_timestamps[vid_key]],
                                   self._tolerance_s, self._return_uint8).squeeze(0)
            for vid_key, (video_path, from_timestamp_s) in located.items()
        }

    decode_video_frames.bcrl_frame_cache = True
    dataset_reader.decode_video_frames = decode_video_frames
    dataset_reader.DatasetReader._query_videos = query_videos
    dataset_reader.DatasetReader.__init__ = init_reader
    lerobot_dataset.LeRobotDataset.__init__ = init_dataset


install()  # on import, so that unpickling a FrameCacheBackend in a fresh interpreter is enough
