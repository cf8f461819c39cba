"""LightningDataModule over a tracked dataset: whole batches sliced from memory-mapped shards.

No per-sample decoding and no per-sample collate: a sampler yields index batches, and each batch is one
fancy-index into the split's uint8 array (loaded into RAM once when it fits, else read from the memmap).

DDP-ready: `batch_size` is the GLOBAL batch. Every rank draws the same seeded permutation of the training
split each epoch (`set_epoch`), cuts it into global batches and takes its own contiguous slice of each
(`batch_size / world_size` samples), so one device and N devices see the same global batches and the same
number of optimiser steps. Validation and test batches are split across ranks the same way (each sample on
exactly one rank, no padding).
"""

from __future__ import annotations

import lightning as L
import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, Sampler

from pipeline.errors import ConfigError
from pipeline.train.settings import DataModuleSpec

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


class ShardedBatchSampler(Sampler):
    """Index batches of one rank: global batches of `batch_size`, this rank's `batch_size / world` slice.

    `shuffle=True`: a fresh permutation per epoch from `seed + epoch` (Lightning calls `set_epoch`), the
    last incomplete global batch dropped. `shuffle=False`: sequential, the last batch kept.
    """

    def __init__(self, n: int, batch_size: int, *, shuffle: bool, seed: int = 0, rank: int = 0, world: int = 1):
        if shuffle and batch_size % world:  # training: every rank an equal share of each global batch
            raise ConfigError("datamodule.batch_size",
                              f"{batch_size} is not divisible by the {world} training processes")
        self.n, self.batch_size, self.shuffle = n, batch_size, shuffle
        self.seed, self.rank, self.world = seed, rank, world
        self.epoch = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def _order(self) -> np.ndarray:
        if not self.shuffle:
            return np.arange(self.n)
        gen = torch.Generator().manual_seed(self.seed * 1_000_003 + self.epoch)
        return torch.randperm(self.n, generator=gen).numpy()

    def _bounds(self, size: int) -> tuple[int, int]:
        per = -(-size // self.world)  # ceil: ranks 0..k get one more when `size` is not divisible
        lo = min(size, self.rank * per)
        return lo, min(size, lo + per)

    def __iter__(self):
        order = self._order()
        for s in range(len(self)):
            glob = order[s * self.batch_size : (s + 1) * self.batch_size]
            lo, hi = self._bounds(len(glob))
            if hi > lo:
                yield glob[lo:hi].tolist()

    def __len__(self) -> int:
        return self.n // self.batch_size if self.shuffle else -(-self.n // self.batch_size)


class PerceptionDataModule(L.LightningDataModule):
    """Train/val/test splits of a tracked dataset (`pipeline.data.Dataset`), batched as its typed spec says
    (:class:`pipeline.train.settings.DataModuleSpec`, built from `conf/datamodule/` and checked before any work);
    `attach(dataset)` once the dataset is open."""

    def __init__(self, spec: DataModuleSpec, dataset=None):
        super().__init__()
        self.batch_size = spec.batch_size
        self.limit_train = spec.limit_train_samples
        self.limit_val = spec.limit_val_samples
        self.eval_batch_size = spec.eval_batch_size
        self.num_workers = spec.num_workers
        self.pin_memory = spec.pin_memory
        self.seed = spec.seed
        self.dataset = None
        self.pose = False  # the labels a pose map trains on: (x, y, θ) (set by the stage from the model)
        self._splits: dict[str, BatchArrays] = {}
        if dataset is not None:
            self.attach(dataset)

    def attach(self, dataset) -> PerceptionDataModule:
        """Use `dataset`; rejects a batch larger than the training split (it would train on zero batches)."""
        n = len(dataset.positions("train"))
        if self.limit_train:
            n = min(n, self.limit_train)
        if self.batch_size > n:
            raise ConfigError("datamodule.batch_size",
                              f"{self.batch_size} is larger than the training split ({n} images): no full batch")
        self.dataset = dataset
        self._splits = {}
        return self

    def train_size(self) -> int:
        return len(self.split("train"))

    def split(self, name: str) -> BatchArrays:
        if name not in self._splits:
            images = self.dataset.images(name)
            pos = self.dataset.poses(name) if self.pose else self.dataset.positions(name)
            limit = {"train": self.limit_train, "val": self.limit_val}.get(name)
            if limit:
                images, pos = images[:limit], pos[:limit]
            self._splits[name] = BatchArrays(images, pos)
        return self._splits[name]

    def _rank_world(self) -> tuple[int, int]:
        trainer = getattr(self, "trainer", None)
        if trainer is None:
            return 0, 1
        return int(trainer.global_rank), int(trainer.world_size)

    def _loader(self, name: str, shuffle: bool) -> DataLoader:
        ds = self.split(name)
        rank, world = self._rank_world()
        batch = self.batch_size if shuffle else self.eval_batch_size * world
        sampler = ShardedBatchSampler(len(ds), batch, shuffle=shuffle, seed=self.seed, rank=rank, world=world)
        return DataLoader(ds, sampler=sampler, batch_size=None, num_workers=self.num_workers,
                          pin_memory=self.pin_memory, persistent_workers=self.num_workers > 0)

    def train_dataloader(self):
        return self._loader("train", shuffle=True)

    def val_dataloader(self):
        return self._loader("val", shuffle=False)

    def test_dataloader(self):
        return self._loader("test", shuffle=False)
