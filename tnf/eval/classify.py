"""The tactile classification task: which object does one tactile image come from?

A small CNN is trained on a set of tactile images and scored on held-out ground-truth touches. The paper's rows
(its Table 1b / 2b): ``Sim`` (ground-truth touches of the training objects only), ``Sim + G`` (the same plus
images generator G made from novel poses) and ``G only``. Every row uses the same network, the same number of
optimisation steps, the same seed and the same test set, so differences come from the training images alone.
With several restarts (``ClassifierConfig.restarts``) each restart draws its own Sim touches, shared by its rows.

Images go in as uint8 ``[N, 3, S, S]`` (the touch-format loader below makes them) and are fed to the network in
[-1, 1]. Everything stays on the device as uint8, and all the classifiers of a call (every row and restart) train
at once on a GPU as one network of grouped convolutions (``StackedClassifiers``), each on its own batches.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterator, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, cast

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from tnf.data.preprocess import SIZE, resize_uint8
from tnf.errors import TnfError
from tnf.eval.settings import ClassifierConfig
from tnf.eval.timing import Phases
from tnf.metrics import exact_fp32_matmul
from tnf.touches import read_touch_records


class TactileClassifier(nn.Module):
    """Conv blocks (3x3 conv, batch norm, ReLU, 2x2 max pool), global average pooling and a linear layer.

    Input ``[B, 3, S, S]`` in [-1, 1]; output logits ``[B, num_classes]``.
    """

    def __init__(self, num_classes: int, width: int = 32, blocks: int = 4):
        super().__init__()
        self.arch = (num_classes, width, blocks)
        layers: list[nn.Module] = []
        c_in = 3
        for i in range(blocks):
            c_out = width * 2 ** min(i, 2)
            layers += [nn.Conv2d(c_in, c_out, 3, padding=1, bias=False), nn.BatchNorm2d(c_out), nn.ReLU(True)]
            layers.append(nn.MaxPool2d(2))
            c_in = c_out
        self.features = nn.Sequential(*layers)
        self.head = nn.Linear(c_in, num_classes)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(x).mean((2, 3)))


def _blocks(image_size: int) -> int:
    """Conv blocks of the classifier at ``image_size`` pixels (up to 4)."""
    return min(4, int(math.log2(image_size)) - 2)


def _scale(x: torch.Tensor) -> torch.Tensor:
    """uint8 -> float in [-1, 1], elementwise."""
    return x.float() / 127.5 - 1.0


def _to_input(x: torch.Tensor, size: int) -> torch.Tensor:
    """uint8 [B, 3, H, W] -> float [B, 3, size, size] in [-1, 1]."""
    x = _scale(x)
    if x.shape[-1] != size or x.shape[-2] != size:
        x = F.interpolate(x, size=(size, size), mode="bilinear", align_corners=False, antialias=True)
    return x


@contextmanager
def reproducible_kernels() -> Iterator[None]:
    """cuDNN's deterministic kernels without autotuning, and full-precision fp32 matrix products, inside the
    block; the caller's settings after it.

    A GPU training stage turns autotuning on and lets fp32 matrix products run in TF32 for the generators
    (``tnf.generators.training``), and a pipeline evaluates in the same process. With autotuned kernels the
    classifier's accuracy differed from run to run for the same images and seed; with TF32 left on, the same
    rows scored differently after a training stage than in a process of their own.
    """
    cudnn = torch.backends.cudnn
    saved = cudnn.benchmark, cudnn.deterministic
    cudnn.benchmark, cudnn.deterministic = False, True
    try:
        with exact_fp32_matmul():
            yield
    finally:
        cudnn.benchmark, cudnn.deterministic = saved


class StackedClassifiers(nn.Module):
    """``M`` TactileClassifiers of one architecture as one network in which each computes what it computes alone.

    Each convolution is a grouped one (group ``m`` is classifier ``m``), each batch norm one over all the
    classifiers' channels (its statistics, the running ones too, are per channel, so per classifier), and the
    head is a batched matrix product. Input ``[B, M * 3, S, S]`` (classifier ``m``'s images in channels
    ``3m .. 3m + 2``); output logits ``[M, B, num_classes]``. ``unstack`` gives the classifiers back.
    """

    def __init__(self, models: Sequence[TactileClassifier]):
        super().__init__()
        if not models or any(m.arch != models[0].arch for m in models):
            raise ValueError("StackedClassifiers needs one or more classifiers of one architecture")
        self.arch, self.num_models = models[0].arch, len(models)
        n = self.num_models
        layers: list[nn.Module] = []
        for i, layer in enumerate(models[0].features):
            state = [m.features[i].state_dict() for m in models]
            if isinstance(layer, nn.Conv2d):
                c_in, c_out = n * layer.in_channels, n * layer.out_channels
                layers.append(nn.Conv2d(c_in, c_out, 3, padding=1, bias=False, groups=n))  # as TactileClassifier's
            elif isinstance(layer, nn.BatchNorm2d):
                layers.append(nn.BatchNorm2d(n * layer.num_features, layer.eps, layer.momentum))
            else:  # ReLU, max pooling: per channel, without parameters
                layers.append(layer)
            # parameters and running statistics side by side; a shared scalar (num_batches_tracked) as it is
            layers[-1].load_state_dict(
                {k: torch.cat([s[k] for s in state]) if v.ndim else v for k, v in state[0].items()}
            )
        self.features = nn.Sequential(*layers)
        self.weight = nn.Parameter(torch.stack([m.head.weight.detach() for m in models]))  # [M, K, C]
        self.bias = nn.Parameter(torch.stack([m.head.bias.detach() for m in models]))  # [M, K]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        f = self.features(x).mean((2, 3))  # [B, M * C]
        if self.num_models == 1:  # a classifier alone: its own head's arithmetic
            return F.linear(f, self.weight[0], self.bias[0]).unsqueeze(0)
        f = f.view(len(f), self.num_models, -1).transpose(0, 1)  # [M, B, C]
        return torch.baddbmm(self.bias.unsqueeze(1), f, self.weight.transpose(1, 2))

    def unstack(self) -> list[TactileClassifier]:
        """The ``M`` classifiers, each with its own weights and running statistics (copies), on this network's device
        and in its mode (training or evaluation). Draws nothing from the global random generator."""
        state = {k: v.detach() for k, v in self.state_dict().items()}
        out = []
        for m in range(self.num_models):
            with torch.device("meta"):
                model = TactileClassifier(*self.arch)
            own = {}
            for k, v in model.state_dict().items():
                if k.startswith("head."):
                    own[k] = state[k.removeprefix("head.")][m].clone()
                else:
                    own[k] = state[k].view(self.num_models, *v.shape)[m].clone() if v.ndim else state[k].clone()
            model.load_state_dict(own, assign=True)
            out.append(model.train(self.training))
        return out


def train_classifier(
    images: torch.Tensor,
    labels: torch.Tensor,
    num_classes: int,
    cfg: ClassifierConfig,
    seed: int = 0,
    device: str = "cpu",
    on_step: Callable[[int], None] | None = None,
    generated: torch.Tensor | None = None,
) -> TactileClassifier:
    """Train a fresh classifier on uint8 images ``[N, 3, H, W]`` with labels ``[N]`` (0..num_classes-1).

    ``generated`` (bool ``[N]``) marks generated images; with ``cfg.real_fraction`` set and both kinds present,
    each batch takes that share from the rest (the ground truth) and the remainder from the generated images.

    The initial weights, batch order and augmentation depend only on ``seed``, and on a GPU cuDNN runs its
    deterministic kernels and matrix products stay in full fp32 (``reproducible_kernels``), so the same images
    and seed train the same classifier whatever ran before in the process. ``on_step(i)`` is called
    after each step (progress bars). This is ``train_classifiers`` with one set, which runs the operations of the
    reference loop (``train_classifier_sequential``) and so trains the same weights bit for bit.
    """
    return train_classifiers([LabelledImages(images, labels, generated)], num_classes, cfg, [seed], device, on_step)[0]


def train_classifiers(
    sets: Sequence[LabelledImages],
    num_classes: int,
    cfg: ClassifierConfig,
    seeds: Sequence[int],
    device: str = "cpu",
    on_step: Callable[[int], None] | None = None,
    at_once: int | None = None,
) -> list[TactileClassifier]:
    """Train one fresh classifier per training set, together -> the classifiers (evaluation mode, on ``device``), in
    the order of ``sets``.

    Classifier ``i`` trains on ``sets[i]`` from ``seeds[i]``: its initial weights, batch order and augmentation are
    those ``train_classifier`` gives that set and seed (``train_classifier_sequential`` is the reference). Up to
    ``at_once`` classifiers take ``cfg.steps`` steps in lockstep as one network (``StackedClassifiers``), each on
    a batch of its own set; classifiers whose batches differ in size (a set smaller than a batch) train in
    separate groups. AdamW is elementwise and the cosine schedule the same for all, so each gets the update it
    gets alone; only the order of floating-point sums differs (not at all in a network of one). ``at_once`` None:
    all of them on a GPU, one at a time on the CPU (where a grouped convolution runs slower than its groups one
    after another). ``on_step(i)`` is called once per classifier after each step ``i``.
    """
    if len(sets) != len(seeds):
        raise ValueError(f"one seed per training set: {len(sets)} sets, {len(seeds)} seeds")
    if at_once is None:
        at_once = len(sets) if torch.device(device).type == "cuda" else 1
    if at_once < 1:
        raise ValueError(f"at_once must be >= 1, got {at_once}")
    plans = []
    for s, seed in zip(sets, seeds, strict=True):
        _check(s.images, s.labels, s.generated)
        plans.append(_Plan(s, seed, *_draws(len(s), s.generated, cfg, seed)))
    out: list[TactileClassifier | None] = [None] * len(plans)
    with reproducible_kernels():
        for size in dict.fromkeys(p.batches.shape[1] for p in plans):  # groups by batch size, in order of sets
            group = [i for i, p in enumerate(plans) if p.batches.shape[1] == size]
            for start in range(0, len(group), at_once):
                chunk = group[start : start + at_once]
                models = _train_group([plans[i] for i in chunk], num_classes, cfg, device, on_step)
                for i, model in zip(chunk, models, strict=True):
                    out[i] = model
    return cast(list[TactileClassifier], out)


def _check(images: torch.Tensor, labels: torch.Tensor, generated: torch.Tensor | None) -> None:
    if len(images) == 0:
        raise TnfError("classifier training set is empty; check the touch and generated datasets")
    if images.dtype != torch.uint8 or images.ndim != 4:
        raise ValueError(f"images must be uint8 [N, 3, H, W], got {images.dtype} {tuple(images.shape)}")
    if generated is not None and generated.shape != labels.shape:
        raise ValueError(f"generated must be a bool mask of shape {tuple(labels.shape)}, got {tuple(generated.shape)}")


class _Batches:
    """Batches of indices into one group of a training set, in a fresh random order each epoch.

    A batch never spans two epochs: when fewer than ``size`` indices are left, the group is reshuffled first.
    """

    def __init__(self, indices: torch.Tensor, size: int, gen: torch.Generator):
        self.indices, self.size, self.gen = indices, size, gen
        self.order, self.pos = self._shuffled(), 0

    def _shuffled(self) -> torch.Tensor:
        return self.indices[torch.randperm(len(self.indices), generator=self.gen)]

    def next(self) -> torch.Tensor:
        if self.pos + self.size > len(self.indices) and self.pos > 0:
            self.order, self.pos = self._shuffled(), 0
        batch = self.order[self.pos : self.pos + self.size]
        self.pos += self.size
        return batch


def _batch_sources(
    n: int, generated: torch.Tensor | None, cfg: ClassifierConfig, gen: torch.Generator
) -> list[_Batches]:
    """One source of the whole set, or (cfg.real_fraction with both kinds present) one per kind."""
    if cfg.real_fraction is None or generated is None or not 0 < int(generated.sum()) < n:
        return [_Batches(torch.arange(n), cfg.batch_size, gen)]
    n_real = min(cfg.batch_size - 1, max(1, round(cfg.real_fraction * cfg.batch_size)))
    mask = generated.bool().cpu()
    return [
        _Batches(torch.nonzero(~mask).flatten(), n_real, gen),
        _Batches(torch.nonzero(mask).flatten(), cfg.batch_size - n_real, gen),
    ]


def _draws(
    n: int, generated: torch.Tensor | None, cfg: ClassifierConfig, seed: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """Every step's batch and shift of one classifier, drawn from ``seed`` in the order of the step-by-step loop:
    indices into its set ``[steps, b]`` (long; ``b`` the same every step, ``cfg.batch_size`` or the set's size if
    smaller) and the shift ``[steps, 2]`` (long ``dx, dy`` in pixels; zeros with ``cfg.shift == 0``)."""
    gen = torch.Generator().manual_seed(seed)
    sources = _batch_sources(n, generated, cfg, gen)
    batches = torch.empty(cfg.steps, sum(min(s.size, len(s.indices)) for s in sources), dtype=torch.long)
    shifts = torch.zeros(cfg.steps, 2, dtype=torch.long)
    for step in range(cfg.steps):
        batches[step] = torch.cat([s.next() for s in sources])
        if cfg.shift > 0:
            shifts[step] = torch.randint(-cfg.shift, cfg.shift + 1, (2,), generator=gen)
    return batches, shifts


@dataclass
class _Plan:
    """One classifier's training: its set, its seed, its batches ``[steps, b]`` and shifts ``[steps, 2]``."""

    data: LabelledImages
    seed: int
    batches: torch.Tensor
    shifts: torch.Tensor


def _initial(num_classes: int, cfg: ClassifierConfig, seed: int) -> TactileClassifier:
    """A fresh classifier whose initial weights depend only on ``seed`` (on the CPU)."""
    torch.manual_seed(seed)
    return TactileClassifier(num_classes, cfg.width, blocks=_blocks(cfg.image_size))


def _train_group(
    plans: Sequence[_Plan],
    num_classes: int,
    cfg: ClassifierConfig,
    device: str,
    on_step: Callable[[int], None] | None,
) -> list[TactileClassifier]:
    """Train the classifiers of ``plans`` (one batch size) in lockstep as one ``StackedClassifiers``."""
    n, size = len(plans), cfg.image_size
    net = StackedClassifiers([_initial(num_classes, cfg, p.seed) for p in plans]).to(device)
    # Every set side by side on the device: uint8, or (sets not at the classifier's size) resized floats.
    resize = any(tuple(p.data.images.shape[-2:]) != (size, size) for p in plans)
    images = torch.cat(
        [
            torch.cat([_to_input(x.to(device), size) for x in p.data.images.split(512)])
            if resize
            else p.data.images.to(device)
            for p in plans
        ]
    )
    labels = torch.cat([p.data.labels for p in plans]).to(device).long()
    offsets = torch.tensor([0, *np.cumsum([len(p.data) for p in plans])[:-1].tolist()])
    batches = (torch.stack([p.batches for p in plans], 2) + offsets).to(device)  # [steps, b, M]
    # Shifting a batch by (dx, dy) with the border pixels repeated reads pixel (y - dy, x - dx), clamped.
    shifts = torch.stack([p.shifts for p in plans], 1)  # [steps, M, 2]
    ramp = torch.arange(size)
    rows = (ramp - shifts[..., 1:]).clamp(0, size - 1).to(device)  # [steps, M, S]
    cols = (ramp - shifts[..., :1]).clamp(0, size - 1).to(device)
    opt = torch.optim.AdamW(net.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda i: 0.5 * (1 + math.cos(math.pi * i / cfg.steps)))
    net.train()
    for step in range(cfg.steps):
        idx = batches[step]  # [b, M]
        x = images[idx]  # [b, M, 3, S, S]
        x = _scale(x) if x.dtype == torch.uint8 else x
        if cfg.shift > 0:
            x = x.gather(3, rows[step][None, :, None, :, None].expand_as(x))
            x = x.gather(4, cols[step][None, :, None, None, :].expand_as(x))
        logits = net(x.reshape(len(x), n * 3, size, size))  # [M, b, K]
        target = labels[idx].T  # [M, b]
        if n == 1:  # the reference's arithmetic
            loss = F.cross_entropy(logits[0], target[0])
        else:  # each classifier's mean loss; their sum gives each its own gradient
            loss = F.cross_entropy(logits.flatten(0, 1), target.flatten(), reduction="none").view(n, -1).mean(1).sum()
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        if on_step is not None:
            for _ in range(n):
                on_step(step)
    return net.eval().unstack()


def train_classifier_sequential(
    images: torch.Tensor,
    labels: torch.Tensor,
    num_classes: int,
    cfg: ClassifierConfig,
    seed: int = 0,
    device: str = "cpu",
    generated: torch.Tensor | None = None,
) -> TactileClassifier:
    """``train_classifier`` as a plain loop over one classifier, drawing each step's batch and shift on the host as
    it goes: the reference that ``train_classifiers`` is checked against (tests, ``bench/classify.py``)."""
    _check(images, labels, generated)
    with reproducible_kernels():
        model = _initial(num_classes, cfg, seed).to(device)
        gen = torch.Generator().manual_seed(seed)
        x_all = images.to(device)
        y_all = labels.to(device).long()
        opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
        sched = torch.optim.lr_scheduler.LambdaLR(opt, lambda i: 0.5 * (1 + math.cos(math.pi * i / cfg.steps)))
        model.train()
        sources = _batch_sources(len(x_all), generated, cfg, gen)
        for _ in range(cfg.steps):
            idx = torch.cat([s.next() for s in sources]).to(device)
            x = _to_input(x_all[idx], cfg.image_size)
            if cfg.shift > 0:
                dx, dy = (torch.randint(-cfg.shift, cfg.shift + 1, (2,), generator=gen)).tolist()
                x = torch.roll(F.pad(x, [cfg.shift] * 4, mode="replicate"), shifts=(dy, dx), dims=(2, 3))
                x = x[..., cfg.shift : cfg.shift + cfg.image_size, cfg.shift : cfg.shift + cfg.image_size]
            loss = F.cross_entropy(model(x), y_all[idx])
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
    return model.eval()


@torch.no_grad()
def predict(model: TactileClassifier, images: torch.Tensor, image_size: int, batch_size: int = 512) -> torch.Tensor:
    """Predicted class ``[N]`` (long, on the CPU) of uint8 images ``[N, 3, H, W]``."""
    device = next(model.parameters()).device
    with reproducible_kernels():
        out = [
            model(_to_input(images[i : i + batch_size].to(device), image_size)).argmax(1).cpu()
            for i in range(0, len(images), batch_size)
        ]
    return torch.cat(out) if out else torch.zeros(0, dtype=torch.long)


def accuracy(model: TactileClassifier, images: torch.Tensor, labels: torch.Tensor, image_size: int) -> float:
    """Classification accuracy in percent on uint8 images ``[N, 3, H, W]`` with labels ``[N]``."""
    if len(images) == 0:
        raise TnfError("classifier test set is empty; the held-out touches (evaluate.classify.test_splits) are missing")
    return float((predict(model, images, image_size) == labels.cpu().long()).float().mean()) * 100.0


@dataclass
class LabelledImages:
    """A classification set: uint8 images ``[N, 3, S, S]``, labels ``[N]`` (indices into the class list) and which
    images are generated (bool ``[N]``; None: none are)."""

    images: torch.Tensor
    labels: torch.Tensor
    generated: torch.Tensor | None = None

    def __post_init__(self) -> None:
        if self.generated is None:
            self.generated = torch.zeros(len(self.labels), dtype=torch.bool)

    @staticmethod
    def concat(sets: Sequence[LabelledImages]) -> LabelledImages:
        return LabelledImages(
            torch.cat([s.images for s in sets]),
            torch.cat([s.labels for s in sets]),
            torch.cat([cast(torch.Tensor, s.generated) for s in sets]),
        )

    def __len__(self) -> int:
        return len(self.labels)


def restart_seed(seed: int, k: int) -> int:
    """The seed of restart ``k`` (0-based) of a row: the first restart uses ``seed`` itself."""
    return seed if k == 0 else seed * 7919 + k


def run_rows(
    train_sets: Mapping[str, LabelledImages] | Callable[[int], Mapping[str, LabelledImages]],
    test: LabelledImages,
    num_classes: int,
    cfg: ClassifierConfig,
    seed: int = 0,
    device: str = "cpu",
    on_step: Callable[[int], None] | None = None,
    at_once: int | None = None,
    phases: Phases | None = None,
) -> dict[str, float]:
    """Train ``cfg.restarts`` classifiers per row (the same seeds and schedule for every row) -> mean accuracy in
    percent per row.

    ``train_sets`` maps each row to its training images, or is a function of a restart's seed
    (``restart_seed``) that returns that mapping: each restart then trains on its own draw, and the rows of one
    restart share it. ``phases`` (``tnf.eval.timing.Phases``) gets the seconds of ``classify.train`` (the
    training sets' draws included) and ``classify.predict``."""
    timer = phases if phases is not None else Phases(device)
    with timer.phase("classify.train"):
        runs = []  # (row, set, seed) of every classifier of the call
        for k in range(cfg.restarts):
            run_seed = restart_seed(seed, k)
            sets = train_sets(run_seed) if callable(train_sets) else train_sets
            runs += [(row, s, run_seed) for row, s in sets.items()]
        every, seeds = [s for _, s, _ in runs], [r for *_, r in runs]
        models = train_classifiers(every, num_classes, cfg, seeds, device, on_step, at_once)
    totals: dict[str, float] = {}
    with timer.phase("classify.predict"):
        for (row, _, _), model in zip(runs, models, strict=True):
            totals[row] = totals.get(row, 0.0) + accuracy(model, test.images, test.labels, cfg.image_size)
    return {row: v / cfg.restarts for row, v in totals.items()}


def subset(n: int, limit: int | None, seed: int) -> np.ndarray:
    """Indices of a random subset of ``limit`` of ``n`` items, in ascending order (all ``n`` when ``limit`` is None
    or not below ``n``): the draw of ``load_touch_images`` and of the ``Sim`` set."""
    if limit is None or n <= limit:
        return np.arange(n)
    return np.sort(np.random.default_rng(seed).choice(n, size=limit, replace=False))


# ---- touch-format folders (the output of `tnf touch` and `tnf generate`) -------------------------------------

# Images resized at once by load_touch_images (a 160 x 120 chunk of 256 is 59 MB in float32).
_RESIZE_CHUNK = 256


def touch_count(folder: str | Path, splits: Sequence[str] | None = None) -> int:
    """How many touches of a touch-format folder ``load_touch_images`` reads with ``splits`` (None: all) and no
    ``limit``: the ``n`` of the draws (``subset``) over them."""
    return sum(1 for t in read_touch_records(Path(folder)) if splits is None or t.split in splits)


def load_touch_images(
    folder: str | Path,
    size: int,
    splits: Sequence[str] | None = None,
    limit: int | None = None,
    seed: int = 0,
    rows: Sequence[int] | np.ndarray | None = None,
    workers: int | None = None,
) -> torch.Tensor:
    """Tactile images of a touch-format folder as uint8 ``[N, 3, size, size]``.

    Images are resized (bilinear, antialiased, aspect ratio not kept) to 128 x 128 like the paired datasets' tactile
    images, then to ``size``.

    ``splits`` keeps touches whose ``split`` is listed (None: all); ``limit`` keeps a random subset of that many
    (chosen with ``seed``, in the manifest's order), the way the ``Sim`` set takes a fixed number per object.
    ``rows`` (instead of ``limit``) reads only those positions among the touches ``splits`` keeps, in the order
    given: a draw made elsewhere (``subset``) without decoding the images it leaves out. ``workers`` threads decode
    the images (None: up to 8, as the CPU has cores); the result is the same whatever their number.
    """
    from PIL import Image

    folder = Path(folder)
    recs = [t for t in read_touch_records(folder) if splits is None or t.split in splits]
    if rows is not None:
        if limit is not None:
            raise ValueError("give limit or rows, not both")
        recs = [recs[int(i)] for i in rows]
    else:
        recs = [recs[i] for i in subset(len(recs), limit, seed)]

    def read(t: Any) -> np.ndarray:
        path = folder / t.image
        try:
            with Image.open(path) as im:
                return np.array(im.convert("RGB"))
        except FileNotFoundError:
            raise TnfError(f"touch image {path} listed in {folder / 'manifest.json'} is missing") from None
        except (OSError, ValueError, SyntaxError) as e:  # truncated or not an image
            raise TnfError(f"touch image {path} is not a readable image ({e}); `tnf clean` its item and redo") from None

    n_workers = min(8, os.cpu_count() or 1) if workers is None else workers
    if n_workers <= 1 or len(recs) < 2:
        decoded = [read(t) for t in recs]
    else:  # PNG decoding releases the GIL; list() re-raises the first error
        with ThreadPoolExecutor(n_workers) as pool:
            decoded = list(pool.map(read, recs))
    out = np.zeros((len(recs), size, size, 3), np.uint8)
    # As the paired datasets do: every tactile image at 128 x 128 first, then the classifier's size. The images of
    # one shape are resized together, a chunk at a time: each comes out as it does resized alone.
    shapes: dict[tuple[int, ...], list[int]] = {}
    for i, img in enumerate(decoded):
        shapes.setdefault(img.shape, []).append(i)
    for idx in shapes.values():
        for c in range(0, len(idx), _RESIZE_CHUNK):
            chunk = idx[c : c + _RESIZE_CHUNK]
            img = resize_uint8(np.stack([decoded[i] for i in chunk]), SIZE)
            out[chunk] = img if size == SIZE else resize_uint8(img, size)
    return torch.from_numpy(out).permute(0, 3, 1, 2).contiguous()
