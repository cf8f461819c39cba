"""LightningDataModule over a tracked dataset: whole batches sliced from memory-mapped shards.

No per-sample decoding and no per-sample collate: a sampler yields index batches, and each batch is one
fancy-index into the split's uint8 array (loaded into RAM once when it fits, else read from the memmap).
"""

from __future__ import annotations

import lightning as L
import numpy as np
import torch
from torch.utils.data import BatchSampler, DataLoader, Dataset, RandomSampler, SequentialSampler

from pipeline.errors import ConfigError

_RAM_LIMIT_BYTES = 4 << 30  # splits smaller than this are copied to RAM (faster random access)


class BatchArrays(Dataset):
    """`ds[list_of_indices] -> (uint8 images (B, H, W, 3), float32 positions (B, 2))`."""

    def __init__(self, images: np.ndarray, positions: np.ndarray):
        if images.nbytes <= _RAM_LIMIT_BYTES:
            images = np.array(images)  # one sequential read of the memmap into RAM
        self.images = images
        self.positions = np.ascontiguousarray(positions, dtype=np.float32)

    def __len__(self) -> int:
        return len(self.positions)

    def __getitem__(self, idx):
        idx = np.sort(np.asarray(idx))  # sorted reads are sequential on a memmap; order within a batch is irrelevant
        return torch.from_numpy(np.asarray(self.images[idx])), torch.from_numpy(self.positions[idx])


class PerceptionDataModule(L.LightningDataModule):
    """Train/val/test splits of a tracked dataset (`pipeline.data.Dataset`)."""

    def __init__(self, dataset, batch_size: int = 128, eval_batch_size: int = 512, seed: int = 0,
                 limit_train: int | None = None):
        super().__init__()
        if not isinstance(batch_size, int) or batch_size <= 0:
            raise ConfigError("trainer.batch_size", f"must be a positive integer, got {batch_size!r}")
        self.dataset = dataset
        self.batch_size = batch_size
        self.eval_batch_size = eval_batch_size
        self.seed = seed
        self.limit_train = limit_train
        self._splits: dict[str, BatchArrays] = {}

    def split(self, name: str) -> BatchArrays:
        if name not in self._splits:
            images, pos = self.dataset.images(name), self.dataset.positions(name)
            if name == "train" and self.limit_train:
                images, pos = images[: self.limit_train], pos[: self.limit_train]
            self._splits[name] = BatchArrays(images, pos)
        return self._splits[name]

    def _loader(self, name: str, shuffle: bool) -> DataLoader:
        ds = self.split(name)
        if shuffle:
            gen = torch.Generator().manual_seed(self.seed)
            sampler = BatchSampler(RandomSampler(ds, generator=gen), self.batch_size, drop_last=True)
        else:
            sampler = BatchSampler(SequentialSampler(ds), self.eval_batch_size, drop_last=False)
        return DataLoader(ds, sampler=sampler, batch_size=None, num_workers=0)

    def train_dataloader(self):
        return self._loader("train", shuffle=True)

    def val_dataloader(self):
        return self._loader("val", shuffle=False)

    def test_dataloader(self):
        return self._loader("test", shuffle=False)
