"""The generator interface: what a registered generator (in-tree or plugin) implements.

A generator is an ``nn.Module`` that holds its networks (generators and discriminators), knows its losses and
its optimisers, and maps a batch of conditions to tactile images. ``GeneratorSystem`` (``system.py``) wraps
any generator for Lightning; nothing in the training loop depends on a particular architecture.

Batches are dicts of float32 tensors in [-1, 1] (see ``tnf.data``): ``rgb`` [B, 3, H, W], ``depth``
[B, 1, H, W], ``background`` [B, 3, H, W] (the sensor's reference image), ``tactile`` [B, 3, H, W] (the target),
plus ``object_id`` [B] (long). H = W = 128 unless a generator's config says otherwise.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any, ClassVar, Protocol

import torch
from torch import nn

from tnf.errors import TnfError


class Optimisation(Protocol):
    """What a generator's ``training_step`` uses to optimise: its optimisers and a backward pass.

    ``GeneratorSystem`` implements it with Lightning's manual optimisation (mixed precision, gradient
    scaling); ``PlainOptimisation`` with plain torch (benchmarks, tests of a single step).
    """

    def optimizers(self) -> Sequence[Any]: ...

    def backward(self, loss: torch.Tensor) -> None: ...


class PlainOptimisation:
    """Plain-torch ``Optimisation``: ``loss.backward()`` and the generator's own optimisers."""

    def __init__(self, generator: Generator):
        self._opts = generator.configure_optimizers()

    def optimizers(self) -> Sequence[torch.optim.Optimizer]:
        return self._opts

    def backward(self, loss: torch.Tensor) -> None:
        loss.backward()


class Generator(nn.Module):
    """Base class of tactile-image generators.

    Subclasses declare a nested ``Config`` dataclass, take it in ``__init__`` and implement ``generate``,
    ``training_step`` and ``configure_optimizers``. ``inputs`` names the conditions ``generate`` takes: batch keys,
    or ``depth_slope`` / ``depth_and_slope``, which tn_cgan and lee derive from ``depth``
    (``tnf.generators.nets.conditioning.conditions``).
    """

    #: Conditions the generator takes when generating (set per instance from the config where configurable).
    inputs: tuple[str, ...] = ("rgb",)
    #: Names of the optimisers ``configure_optimizers`` returns, in order (used for learning-rate logging); a
    #: generator may return only the first ones (tn_cgan without its adversarial term: the generator's alone).
    optimizer_names: ClassVar[tuple[str, ...]] = ("g", "d")

    def __init__(self) -> None:
        super().__init__()
        self._frozen: set[str] = set()

    # -- to implement -----------------------------------------------------------------------------------
    def generate(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """Tactile images [B, 3, H, W] in [-1, 1] for the conditions in ``batch`` (no gradients needed)."""
        raise NotImplementedError

    def training_step(self, batch: dict[str, torch.Tensor], opt: Optimisation) -> dict[str, torch.Tensor]:
        """One optimisation step of every network on ``batch``; returns detached losses by name (``loss_g``,
        ``loss_d``, ...) for logging. Call ``opt.backward(loss)`` instead of ``loss.backward()``. A GAN that also
        returns ``d_real`` and ``d_fake`` (its discriminator's mean outputs, 1 = real) gets a saturated
        discriminator reported each epoch (``train/d_saturated``, ``GeneratorSystem``)."""
        raise NotImplementedError

    def configure_optimizers(self) -> list[torch.optim.Optimizer]:
        """The optimisers, in the order of ``optimizer_names``; build them over ``self.trainable(module)``."""
        raise NotImplementedError

    def fixed_graph(self) -> bool:
        """True when every training step runs one backward pass through the same parameters. DDP then uses a
        static graph instead of searching each step for parameters without gradients (a GAN's alternating
        updates cannot: their steps back-propagate through different networks)."""
        return False

    # -- shared -----------------------------------------------------------------------------------------
    def check_batch(self, batch: dict[str, torch.Tensor], keys: Iterable[str]) -> None:
        missing = [k for k in keys if k not in batch]
        if missing:
            raise TnfError(
                f"generator {type(self).__name__} needs batch keys {sorted(keys)}; missing {missing} "
                f"(batch has {sorted(batch)})"
                + ("; the prior comes with datasets made with pair.prior=true" if "prior" in missing else "")
                + ("; surface points come with datasets made with pair.points=true" if "points" in missing else "")
                + ("; the force comes with datasets made with pair.force=true" if "force" in missing else "")
            )

    def freeze(self, prefixes: Iterable[str]) -> list[str]:
        """Freeze every parameter whose name starts with one of ``prefixes`` (e.g. ``net_g.encoders.rgb``).

        Frozen parameters are left out of the optimisers and their modules stay in eval mode (batch-norm
        statistics do not move). Returns the frozen parameter names; a prefix matching nothing is an error.
        """
        names = [n for n, _ in self.named_parameters()]
        out = []
        for prefix in prefixes:
            hit = [n for n in names if n == prefix or n.startswith(prefix + ".")]
            if not hit:
                tops = sorted({n.rsplit(".", 2)[0] for n in names})
                raise TnfError(f"freeze: {prefix!r} matches no parameter; modules: {', '.join(tops[:40])}")
            out += hit
        self._frozen.update(out)
        for n, p in self.named_parameters():
            if n in self._frozen:
                p.requires_grad_(False)
        self.train(self.training)
        return out

    def trainable(self, *modules: nn.Module) -> list[nn.Parameter]:
        """Parameters of ``modules`` that are not frozen (what optimisers should receive)."""
        ids = {id(p) for n, p in self.named_parameters() if n in self._frozen}
        return [p for m in modules for p in m.parameters() if id(p) not in ids]

    def set_requires_grad(self, module: nn.Module, flag: bool) -> None:
        """Toggle gradients of ``module`` (e.g. the discriminator during the generator's step); frozen
        parameters stay frozen."""
        ids = {id(p) for n, p in self.named_parameters() if n in self._frozen}
        for p in module.parameters():
            if id(p) not in ids:
                p.requires_grad_(flag)

    def train(self, mode: bool = True) -> Generator:
        super().train(mode)
        if mode and self._frozen:
            modules = dict(self.named_modules())
            for n in self._frozen:
                owner = n.rsplit(".", 1)[0]
                if owner in modules:
                    modules[owner].eval()
        return self
