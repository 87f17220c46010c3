"""Training on a CUDA GPU with bf16 mixed precision through Lightning (skipped without a GPU)."""

import pytest
import torch

from tests.generators.synthetic import SyntheticPairs, make_pairs
from tnf.generators import GeneratorSystem, load_generator
from tnf.generators.training import fit

pytestmark = [pytest.mark.gpu, pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")]


@pytest.mark.parametrize("name", ["tn_cgan", "lee", "cyclegan"])
def test_bf16_training_on_gpu(tmp_path, name):
    torch.manual_seed(0)
    system = GeneratorSystem({"name": name, "ngf": 16, "ndf": 16}, epochs=2, decay_epochs=1, finite_check_every=1)
    dm = SyntheticPairs(n_train=64, n_val=16, size=128, batch_size=16)
    summary = fit(
        system,
        dm,
        tmp_path / "run",
        config={"name": name},
        trainer_cfg={"accelerator": "gpu", "devices": 1, "precision": "bf16-mixed"},
        progress=False,
    )
    assert summary["epochs"] == 2 and 0 < summary["last"]["val_ssim"] <= 1
    loaded = load_generator(tmp_path / "run" / "best.ckpt", "cuda")
    out = loaded.generate({k: v.cuda() for k, v in make_pairs(4, 128).items()})
    assert out.shape == (4, 3, 128, 128) and torch.isfinite(out).all()
