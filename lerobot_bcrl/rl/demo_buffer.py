"""The demonstrations of the BC term, held in memory and sampled as endless shuffled minibatches.

LeRobotDataset decodes one frame per `__getitem__`; a BC minibatch beside every PPO minibatch would spend most of
the update there. Frames are read once (cameras kept as uint8) and batches preprocessed like lerobot-train's
(normalised, aux.* kept).
"""

from __future__ import annotations

import torch
from torch import Tensor
from tqdm import tqdm

from lerobot_bcrl.features import IMAGES_PREFIX


class DemoBuffer:
    def __init__(self, dataset, batch_size: int, seed: int, preprocessor):
        loader = torch.utils.data.DataLoader(dataset, batch_size=256, shuffle=False, num_workers=0)
        # each chunk compacted as it is read: the float frames of a whole image dataset are 4x its uint8 frames
        # (20,000 frames of 128x128: 3.9 GB) and would be held several times over by the concatenation
        chunks = [{key: self._compact(key, value) for key, value in chunk.items() if isinstance(value, Tensor)}
                  for chunk in tqdm(loader, desc="loading demonstrations", leave=False)]
        self.frames = {key: torch.cat([c[key] for c in chunks]) for key in chunks[0]}
        self.n_frames = len(next(iter(self.frames.values())))
        self.batch_size = min(batch_size, self.n_frames)
        self.generator = torch.Generator().manual_seed(seed)
        self.preprocessor = preprocessor

    @staticmethod
    def _compact(key: str, value: Tensor) -> Tensor:
        return (value * 255).round().to(torch.uint8) if key.startswith(IMAGES_PREFIX) else value

    def __iter__(self):
        return self

    def __next__(self) -> dict[str, Tensor]:
        index = torch.randint(self.n_frames, (self.batch_size,), generator=self.generator)
        batch = {key: value[index] for key, value in self.frames.items()}
        batch.update({key: value.float() / 255 for key, value in batch.items() if value.dtype == torch.uint8})
        return self.preprocessor(batch)
