"""A tiny synthetic paired task made by code: the tactile image is the background plus a dark blob whose
position and size follow the depth image (a bump where the object presses), as a real touch does."""

from __future__ import annotations

import lightning as L
import torch
from torch.utils.data import DataLoader, Dataset


def make_pairs(n: int, size: int = 32, seed: int = 0) -> dict[str, torch.Tensor]:
    """``n`` pairs as float32 tensors in [-1, 1]: rgb [n,3,S,S], depth [n,1,S,S], background [n,3,S,S],
    tactile [n,3,S,S] and object_id [n]."""
    g = torch.Generator().manual_seed(seed)
    yy, xx = torch.meshgrid(torch.linspace(-1, 1, size), torch.linspace(-1, 1, size), indexing="ij")
    # One sensor background for all pairs: a colour gradient with a grid of marker dots (as on a gel).
    dots = torch.cos(4 * torch.pi * xx) * torch.cos(4 * torch.pi * yy)
    bg = torch.stack([0.4 * xx, 0.3 * yy, 0.2 * (xx * yy)]) + torch.tensor([0.1, -0.1, 0.2])[:, None, None]
    bg = bg - 0.4 * (dots > 0.7).float()
    centre = torch.rand(n, 2, generator=g) * 1.0 - 0.5  # blob centre in [-0.5, 0.5]^2
    radius = 0.3 + 0.3 * torch.rand(n, generator=g)  # blob radius in normalised image units
    d2 = (xx[None] - centre[:, 0, None, None]) ** 2 + (yy[None] - centre[:, 1, None, None]) ** 2
    bump = torch.exp(-d2 / (radius[:, None, None] ** 2))  # [n, S, S] in (0, 1]
    depth = (1 - 2 * bump)[:, None]  # near (-1) at the contact, far (1) elsewhere
    shade = torch.tensor([0.8, 0.3, -0.2])[:, None, None]
    rgb = (bump[:, None] * shade - 0.3).clamp(-1, 1)
    tactile = (bg[None] - 0.8 * bump[:, None] * torch.tensor([1.0, 0.6, 0.3])[:, None, None]).clamp(-1, 1)
    return {
        "rgb": rgb.float(),
        "depth": depth.float(),
        "background": bg[None].expand(n, -1, -1, -1).contiguous().float(),
        "tactile": tactile.float(),
        "object_id": torch.arange(n) % 2,
    }


class TensorPairs(Dataset):
    """Items of a dict of tensors (as ``tnf.data.PairDataset`` yields them)."""

    def __init__(self, pairs: dict[str, torch.Tensor]):
        self.pairs = pairs

    def __len__(self) -> int:
        return len(self.pairs["rgb"])

    def __getitem__(self, i: int) -> dict[str, torch.Tensor]:
        return {k: v[i] for k, v in self.pairs.items()}


class SyntheticPairs(L.LightningDataModule):
    """Train and val loaders over synthetic pairs (val: other pairs of the same task)."""

    def __init__(self, n_train: int = 8, n_val: int = 4, size: int = 32, batch_size: int = 4, seed: int = 0):
        super().__init__()
        self.train = make_pairs(n_train, size, seed)
        self.val = make_pairs(n_val, size, seed + 1)
        self.batch_size = batch_size

    def train_dataloader(self) -> DataLoader:
        return DataLoader(TensorPairs(self.train), batch_size=self.batch_size, shuffle=True)

    def val_dataloader(self) -> DataLoader:
        return DataLoader(TensorPairs(self.val), batch_size=self.batch_size)
