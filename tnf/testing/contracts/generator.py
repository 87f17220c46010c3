"""The generator contract suite, and the random batch it trains and generates on."""

from __future__ import annotations

import json
from typing import Any, ClassVar

import pytest

from tnf.registry import (
    GENERATORS,
)
from tnf.testing.contracts.base import _ComponentContract


# -- generators -------------------------------------------------------------------------------------
def random_batch(batch_size: int = 2, size: int = 128, seed: int = 0) -> dict[str, Any]:
    """A batch of conditions and targets as ``tnf.data`` yields them: float32 in [-1, 1], ``object_id`` long."""
    import torch

    g = torch.Generator().manual_seed(seed)

    def img(c: int) -> torch.Tensor:
        return torch.rand(batch_size, c, size, size, generator=g) * 2 - 1

    return {
        "rgb": img(3),
        "depth": img(1),
        "background": img(3),
        "tactile": img(3),
        "object_id": torch.arange(batch_size, dtype=torch.long),
    }


class GeneratorContract(_ComponentContract):
    """A generator (``tnf.generators.Generator`` subclass) builds from its name, generates, trains and saves.

    Checks: registration and documented Config; config round trip; built from its registry name it is a
    ``Generator``; ``generate`` on a batch of ``batch_size`` gives ``[B, 3, 128, 128]`` in [-1, 1]; one
    ``training_step`` returns finite losses and changes the weights; a Lightning checkpoint stores the
    registry name and config (no class paths: it loads with ``weights_only=True``) and loads back.
    Set ``params`` to make the networks tiny.
    """

    registry = GENERATORS
    batch_size: ClassVar[int] = 2
    image_size: ClassVar[int] = 128

    @pytest.fixture
    def generator(self) -> Any:
        import torch

        torch.manual_seed(0)
        return GENERATORS.build(self.spec())

    def test_is_a_generator(self, generator):
        from tnf.generators import Generator

        assert isinstance(generator, Generator)
        from tnf.generators.nets.conditioning import CHANNELS

        # Batch keys tnf serves, or conditions derived from them (depth_slope, depth_and_slope).
        assert generator.inputs and set(generator.inputs) <= set(CHANNELS)

    def test_generate_shape_and_range(self, generator):
        import torch

        generator.eval()
        with torch.no_grad():
            out = generator.generate(random_batch(self.batch_size, self.image_size))
        assert out.shape == (self.batch_size, 3, self.image_size, self.image_size)
        assert out.dtype == torch.float32 and torch.isfinite(out).all()
        assert out.min() >= -1 and out.max() <= 1

    def test_one_training_step(self, generator):
        import torch

        from tnf.generators import PlainOptimisation

        generator.train()
        before = {k: v.detach().clone() for k, v in generator.named_parameters()}
        losses = generator.training_step(random_batch(self.batch_size, self.image_size), PlainOptimisation(generator))
        assert losses and all(torch.isfinite(v).all() and v.numel() == 1 for v in losses.values()), losses
        changed = [k for k, v in generator.named_parameters() if not torch.equal(v, before[k])]
        assert changed, "a training step must update some weights"

    @pytest.mark.filterwarnings("ignore:.*validation_step.*:UserWarning")
    def test_checkpoint_stores_name_not_class_path(self, tmp_path):
        import lightning as L
        import torch

        from tnf.generators import GeneratorSystem, load_generator
        from tnf.generators.system import read_checkpoint

        system = GeneratorSystem(self.spec(), epochs=1, decay_epochs=0, grid_rows=0)
        loader = torch.utils.data.DataLoader([_unbatch(random_batch(1, self.image_size, s)) for s in range(2)], 2)
        # No steps: the training step has its own test; this one is about what a checkpoint stores.
        trainer = L.Trainer(
            max_steps=0,
            accelerator="cpu",
            logger=False,
            enable_checkpointing=False,
            enable_progress_bar=False,
            enable_model_summary=False,
            limit_val_batches=0,
            default_root_dir=tmp_path,
        )
        trainer.fit(system, loader)
        path = tmp_path / "last.ckpt"
        trainer.save_checkpoint(path)
        ckpt = read_checkpoint(path)  # loads with weights_only=True: no pickled classes inside
        assert ckpt["tnf"]["generator"]["name"] == self.name
        module = type(system.generator).__module__
        text = json.dumps({k: v for k, v in ckpt.items() if k in ("tnf", "hyper_parameters")}, default=str)
        assert module not in text, f"the checkpoint names a class path ({module})"
        loaded = load_generator(path, expected=self.name)
        for k, v in system.state_dict().items():
            assert torch.equal(v.cpu(), loaded.state_dict()[k].cpu()), k


def _unbatch(batch: dict[str, Any]) -> dict[str, Any]:
    return {k: v[0] for k, v in batch.items()}
