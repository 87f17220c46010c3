"""The tactile object classifier and the touch-format image loader."""

import numpy as np
import pytest
import torch

from tests.eval.eval_fixtures import tactile_image, write_touch_folder
from tnf.errors import TnfError
from tnf.eval.classify import (
    ClassifierConfig,
    LabelledImages,
    accuracy,
    load_touch_images,
    restart_seed,
    run_rows,
    subset,
    train_classifier,
)

TINY = ClassifierConfig(image_size=32, width=8, steps=60, batch_size=16, lr=3e-3, shift=2)


def _separable(n_per_class: int, seed: int) -> LabelledImages:
    rng = np.random.default_rng(seed)
    imgs, labels = [], []
    for label in range(3):
        for _ in range(n_per_class):
            imgs.append(tactile_image(label, rng, 64, 64))
            labels.append(label)
    x = torch.from_numpy(np.stack(imgs)).permute(0, 3, 1, 2).contiguous()
    return LabelledImages(x, torch.tensor(labels))


def test_classifier_learns_a_separable_set():
    train, test = _separable(12, seed=0), _separable(8, seed=1)
    model = train_classifier(train.images, train.labels, 3, TINY, seed=0)
    assert accuracy(model, test.images, test.labels, TINY.image_size) >= 95.0


def test_same_seed_same_classifier_and_rows_share_the_schedule():
    train, test = _separable(6, seed=2), _separable(4, seed=3)
    cfg = ClassifierConfig(image_size=32, width=4, steps=5, batch_size=8)
    a = train_classifier(train.images, train.labels, 3, cfg, seed=7)
    b = train_classifier(train.images, train.labels, 3, cfg, seed=7)
    for pa, pb in zip(a.state_dict().values(), b.state_dict().values(), strict=True):
        assert torch.equal(pa, pb)
    steps = []
    rows = run_rows({"A": train, "B": LabelledImages.concat([train, train])}, test, 3, cfg, on_step=steps.append)
    assert set(rows) == {"A", "B"} and all(0 <= v <= 100 for v in rows.values())
    assert len(steps) == 2 * cfg.steps  # a larger training set gets no extra steps


def test_restarts_average_classifiers_trained_from_their_own_seeds():
    train, test = _separable(6, seed=4), _separable(4, seed=5)
    one = ClassifierConfig(image_size=32, width=4, steps=5, batch_size=8)
    two = ClassifierConfig(image_size=32, width=4, steps=5, batch_size=8, restarts=2)
    first = run_rows({"A": train}, test, 3, one, seed=3)["A"]
    again = accuracy(
        train_classifier(train.images, train.labels, 3, one, seed=3 * 7919 + 1), test.images, test.labels, 32
    )
    steps = []
    assert run_rows({"A": train}, test, 3, two, seed=3, on_step=steps.append)["A"] == pytest.approx((first + again) / 2)
    assert len(steps) == 2 * one.steps
    with pytest.raises(TnfError, match="restarts must be >= 1"):
        ClassifierConfig(restarts=0).validate()


def test_restarts_draw_their_own_training_sets_shared_by_their_rows():
    train, test = _separable(6, seed=4), _separable(4, seed=5)
    cfg = ClassifierConfig(image_size=32, width=4, steps=5, batch_size=8, restarts=2)
    seen = []

    def draw(run_seed: int) -> dict[str, LabelledImages]:
        seen.append(run_seed)
        idx = torch.from_numpy(subset(len(train), 9, run_seed))
        part = LabelledImages(train.images[idx], train.labels[idx])
        return {"A": part, "B": LabelledImages.concat([part, part])}

    rows = run_rows(draw, test, 3, cfg, seed=3)
    assert seen == [3, restart_seed(3, 1)] == [3, 3 * 7919 + 1]
    one = ClassifierConfig(image_size=32, width=4, steps=5, batch_size=8)
    expect = {}
    for s in list(seen):
        for row, part in draw(s).items():
            model = train_classifier(part.images, part.labels, 3, one, seed=s)
            expect[row] = expect.get(row, 0.0) + accuracy(model, test.images, test.labels, 32) / 2
    assert rows == pytest.approx(expect)


def test_subset_is_a_seeded_sorted_draw():
    a = subset(20, 5, seed=1)
    assert len(a) == 5 and len(set(a.tolist())) == 5 and (np.diff(a) > 0).all() and a.max() < 20
    assert np.array_equal(a, subset(20, 5, seed=1))
    assert not np.array_equal(a, subset(20, 5, seed=2))
    assert np.array_equal(subset(4, 5, seed=1), np.arange(4))
    assert np.array_equal(subset(4, None, seed=1), np.arange(4))


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)])
def test_classifier_trains_reproducibly_after_a_training_stage_left_its_settings(device):
    """A GPU training stage leaves cuDNN autotuning on and fp32 matrix products in TF32. The classifier switches
    to deterministic kernels and full fp32 while it trains (seen from inside its steps), restores
    the caller's settings, and trains the same weights as with a fresh process's settings. On an H100,
    autotuning moved weights by up to 0.15, and seed 0's Sim row read 47.6 % after a training stage in the same
    process, 47.3 % in a process of its own."""
    if device == "cuda" and not torch.cuda.is_available():
        pytest.skip("needs a CUDA GPU")
    cudnn = torch.backends.cudnn

    def settings() -> tuple[bool, bool, str]:
        return cudnn.benchmark, cudnn.deterministic, torch.get_float32_matmul_precision()

    saved = settings()
    train = _separable(6, seed=4)
    cfg = ClassifierConfig(image_size=32, width=4, steps=20, batch_size=8)
    try:
        runs, seen = [], []
        for leftover in [(True, False, "high"), (False, False, "highest")]:
            cudnn.benchmark, cudnn.deterministic = leftover[:2]
            torch.set_float32_matmul_precision(leftover[2])
            runs.append(
                train_classifier(train.images, train.labels, 3, cfg, 0, device, lambda _: seen.append(settings()))
            )
            assert settings() == leftover
        assert set(seen) == {(False, True, "highest")} and len(seen) == 2 * cfg.steps
        for pa, pb in zip(runs[0].state_dict().values(), runs[1].state_dict().values(), strict=True):
            assert torch.equal(pa, pb)
    finally:
        cudnn.benchmark, cudnn.deterministic = saved[:2]
        torch.set_float32_matmul_precision(saved[2])


def test_config_rejects_unknown_and_bad_values():
    with pytest.raises(TnfError, match="evaluate.classifier.epochs"):
        ClassifierConfig.from_dict({"epochs": 3})
    with pytest.raises(TnfError, match="image_size"):
        ClassifierConfig.from_dict({"image_size": 8})


def test_load_touch_images_filters_splits_and_subsamples(tmp_path):
    folder = write_touch_folder(tmp_path / "ball", "ball", 0, {"train": 5, "novel_view": 3})
    x = load_touch_images(folder, 32, splits=["train"])
    assert x.shape == (5, 3, 32, 32) and x.dtype == torch.uint8
    assert load_touch_images(folder, 128, splits=["novel_view"]).shape == (3, 3, 128, 128)
    a = load_touch_images(folder, 32, splits=["train"], limit=2, seed=1)
    b = load_touch_images(folder, 32, splits=["train"], limit=2, seed=1)
    assert a.shape[0] == 2 and torch.equal(a, b)
    (folder / "images" / "00000.png").unlink()
    with pytest.raises(TnfError, match="00000.png"):
        load_touch_images(folder, 32)


def test_real_fraction_draws_each_batch_from_both_kinds_and_leaves_one_kind_sets_alone():
    from tnf.eval.classify import _batch_sources

    cfg = ClassifierConfig(image_size=32, width=4, steps=5, batch_size=8, real_fraction=0.25)
    generated = torch.zeros(30, dtype=torch.bool)
    generated[6:] = True  # 6 ground-truth images, 24 generated
    sources = _batch_sources(30, generated, cfg, torch.Generator().manual_seed(0))
    seen_real = []
    for _ in range(12):
        idx = torch.cat([s.next() for s in sources])
        assert len(idx) == 8 and int((~generated[idx]).sum()) == 2  # a quarter of each batch
        seen_real += idx[~generated[idx]].tolist()
    # every ground-truth image once per epoch of the ground truth (3 batches of 2), never twice in one
    for epoch in range(4):
        assert sorted(seen_real[6 * epoch : 6 * epoch + 6]) == list(range(6))
    # a set of one kind is drawn as without real_fraction: the same classifier, weight for weight
    train = _separable(6, seed=5)
    plain = ClassifierConfig(image_size=32, width=4, steps=5, batch_size=8)
    a = train_classifier(train.images, train.labels, 3, plain, seed=1)
    for mask in (None, torch.ones(len(train), dtype=torch.bool)):
        b = train_classifier(train.images, train.labels, 3, cfg, seed=1, generated=mask)
        for pa, pb in zip(a.state_dict().values(), b.state_dict().values(), strict=True):
            assert torch.equal(pa, pb)
    mixed = torch.arange(len(train)) % 2 == 0
    c = train_classifier(train.images, train.labels, 3, cfg, seed=1, generated=mixed)
    assert any(not torch.equal(pa, pc) for pa, pc in zip(a.state_dict().values(), c.state_dict().values()))


def test_labelled_images_keep_which_are_generated_through_concat():
    real = _separable(2, seed=6)
    fake = LabelledImages(real.images, real.labels, torch.ones(len(real), dtype=torch.bool))
    both = LabelledImages.concat([real, fake])
    assert both.generated is not None and both.generated.tolist() == [False] * 6 + [True] * 6


@pytest.mark.parametrize("bad", [0, 1, 1.5, -0.2, True, "half"])
def test_real_fraction_must_be_a_share(bad):
    with pytest.raises(TnfError, match="real_fraction must be null or a number in"):
        ClassifierConfig.from_dict({"real_fraction": bad})
