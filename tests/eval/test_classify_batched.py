"""Classifiers trained together as one network against the reference loop that trains one at a time."""

import dataclasses

import numpy as np
import pytest
import torch

from tnf.eval.classify import (
    ClassifierConfig,
    LabelledImages,
    StackedClassifiers,
    TactileClassifier,
    accuracy,
    predict,
    restart_seed,
    run_rows,
    train_classifier,
    train_classifier_sequential,
    train_classifiers,
)

# A few steps, for weights; a classifier that learns the task, for accuracies (fewer steps leave it at chance).
SHORT = ClassifierConfig(image_size=32, width=4, steps=4, batch_size=8, lr=3e-3, shift=2, real_fraction=0.5)
LEARNS = ClassifierConfig(image_size=32, width=8, steps=60, batch_size=16, lr=3e-3, shift=2, real_fraction=0.5)

devices = ["cpu", pytest.param("cuda", marks=pytest.mark.gpu)]


def _images(n_per_class: int, seed: int, side: int = 32, generated: bool = False) -> LabelledImages:
    """uint8 images ``[3 * n_per_class, 3, side, side]`` of 3 classes: a round blob, a horizontal or a vertical bar
    at a random place on a bluish background, with noise."""
    rng = np.random.default_rng(seed)
    labels = np.repeat(np.arange(3), n_per_class)
    yy, xx = np.mgrid[0:side, 0:side].astype(np.float32) / side
    x = []
    for k in labels:
        cy, cx = rng.uniform(0.3, 0.7, 2)
        sy, sx = [(0.12, 0.12), (0.05, 0.3), (0.3, 0.05)][k]
        blob = np.exp(-(((yy - cy) / sy) ** 2 + ((xx - cx) / sx) ** 2))
        img = (
            np.stack([60 + 40 * xx, 90 + 20 * yy, np.full_like(xx, 150)])
            + blob * np.array([80, 60, -40])[:, None, None]
        )
        x.append(np.clip(img + rng.normal(0, 6, img.shape), 0, 255).astype(np.uint8))
    mask = torch.full((len(labels),), generated)
    return LabelledImages(torch.from_numpy(np.stack(x)), torch.from_numpy(labels), mask)


def _sets() -> list[LabelledImages]:
    """Sets of different sizes (two smaller than a batch of 16), mixed ground-truth and generated images, and images
    at twice the classifier's size (resized as they are read)."""
    sim, gen = _images(4, seed=0), _images(8, seed=1, generated=True)
    return [sim, LabelledImages.concat([sim, gen]), gen, _images(2, seed=2), _images(6, seed=3, side=64)]


def _max_diff(a: torch.nn.Module, b: torch.nn.Module) -> float:
    """Largest difference of any parameter or running statistic of two classifiers."""
    sa, sb = a.state_dict(), b.state_dict()
    assert sa.keys() == sb.keys()
    return max(float((sa[k].double().cpu() - sb[k].double().cpu()).abs().max()) for k in sa)


def _skip_without(device: str) -> None:
    if device == "cuda" and not torch.cuda.is_available():
        pytest.skip("needs a CUDA GPU")


@pytest.mark.parametrize("device", devices)
def test_one_classifier_trains_as_the_reference_loop(device):
    """Alone, a classifier gets the reference's weights and running statistics bit for bit: augmented, resized and
    drawn half from the ground truth."""
    _skip_without(device)
    for s, seed in zip(_sets(), [0, 1, 2, 3, 4], strict=True):
        ref = train_classifier_sequential(s.images, s.labels, 3, SHORT, seed, device, s.generated)
        got = train_classifier(s.images, s.labels, 3, SHORT, seed, device, generated=s.generated)
        assert _max_diff(ref, got) == 0.0
        assert not got.training and next(got.parameters()).device.type == device


@pytest.mark.parametrize("device", devices)
def test_classifiers_trained_together_match_the_reference_loop(device):
    """Trained together, each classifier keeps its own initial weights, batches, shifts and training set: after a
    few steps its weights and running statistics agree with the reference's to float summation order, and a
    classifier trained until it learns the task predicts each test image as the reference does.

    Over many steps Adam lets summation-order differences grow (the reference loop itself, its initial weights
    scaled by 1 + 1e-7, ends 60 steps ~1e-3 away), so weights are compared after a few steps."""
    _skip_without(device)
    sets, seeds = _sets(), [5, 5, 6, 7, 8]
    steps: list[int] = []
    together = train_classifiers(sets, 3, SHORT, seeds, device, steps.append, at_once=len(sets))
    assert len(steps) == len(sets) * SHORT.steps and sorted(set(steps)) == list(range(SHORT.steps))
    for s, seed, got in zip(sets, seeds, together, strict=True):
        ref = train_classifier_sequential(s.images, s.labels, 3, SHORT, seed, device, s.generated)
        assert _max_diff(ref, got) <= 1e-5
    # the same set and seed train alike in another group; another seed trains another classifier
    assert _max_diff(together[1], train_classifiers(sets[:2], 3, SHORT, seeds[:2], device, at_once=2)[1]) <= 1e-5
    assert _max_diff(together[1], train_classifiers(sets[1:2], 3, SHORT, [6], device)[0]) > 1e-3

    test = _images(8, seed=9)
    together = train_classifiers(sets, 3, LEARNS, seeds, device, at_once=len(sets))
    scores = []
    for s, seed, got in zip(sets, seeds, together, strict=True):
        ref = train_classifier_sequential(s.images, s.labels, 3, LEARNS, seed, device, s.generated)
        assert torch.equal(predict(ref, test.images, 32), predict(got, test.images, 32))
        scores.append(accuracy(got, test.images, test.labels, 32))
    assert max(scores) > 90.0 and min(scores) < 80.0  # the rows differ: the comparison is not between perfect scores


def test_rows_and_restarts_trained_together_score_as_one_at_a_time():
    """run_rows with every classifier in one network gives each row the accuracy of the reference loop."""
    sim_pool, gen, test = _images(8, seed=10), _images(6, seed=11, generated=True), _images(6, seed=12)
    cfg = dataclasses.replace(LEARNS, restarts=2)

    def draw(run_seed: int) -> dict[str, LabelledImages]:
        idx = torch.from_numpy(np.random.default_rng(run_seed).choice(len(sim_pool), 9, replace=False))
        sim = LabelledImages(sim_pool.images[idx], sim_pool.labels[idx])
        return {"Sim": sim, "Sim + G": LabelledImages.concat([sim, gen]), "G only": gen}

    steps = []
    rows = run_rows(draw, test, 3, cfg, seed=3, on_step=steps.append, at_once=6)
    assert len(steps) == 6 * cfg.steps
    expect: dict[str, float] = {}
    for k in range(cfg.restarts):
        s = restart_seed(3, k)
        for row, part in draw(s).items():
            model = train_classifier_sequential(part.images, part.labels, 3, cfg, s, "cpu", part.generated)
            expect[row] = expect.get(row, 0.0) + accuracy(model, test.images, test.labels, 32) / cfg.restarts
    assert rows == pytest.approx(expect)
    assert len(set(rows.values())) > 1  # the rows differ: the comparison is not between perfect scores


def test_stacked_network_keeps_each_classifiers_batch_norm_statistics():
    """In training mode each classifier's batch norm normalises over its own images and updates its own running
    statistics; in evaluation mode each uses its own. Stacking and unstacking returns the classifiers unchanged."""
    models = []
    for seed in range(3):
        torch.manual_seed(seed)
        m = TactileClassifier(5, width=4, blocks=2)
        for layer in m.features:
            if isinstance(layer, torch.nn.BatchNorm2d):
                layer.running_mean.uniform_(-1, 1)
                layer.running_var.uniform_(0.5, 2)
        models.append(m)
    net = StackedClassifiers(models)
    for a, b in zip(models, net.unstack(), strict=True):
        assert _max_diff(a, b) == 0.0
    x = torch.randn(6, 3, 3, 16, 16)  # [B, M, 3, S, S]: each classifier its own images
    with torch.no_grad():
        net.eval()
        out = net(x.reshape(6, 9, 16, 16))
        for m, model in enumerate(models):
            assert torch.allclose(out[m], model.eval()(x[:, m]), atol=1e-5)
        net.train()
        out = net(x.reshape(6, 9, 16, 16))
        for m, (model, back) in enumerate(zip(models, net.unstack(), strict=True)):
            assert torch.allclose(out[m], model.train()(x[:, m]), atol=1e-5)
            assert _max_diff(model, back) <= 1e-6  # the running statistics each updated from its own batch
    with pytest.raises(ValueError, match="one architecture"):
        StackedClassifiers([models[0], TactileClassifier(5, width=8, blocks=2)])


def test_train_classifiers_checks_its_arguments():
    s = _images(2, seed=0)
    with pytest.raises(ValueError, match="one seed per training set"):
        train_classifiers([s, s], 3, SHORT, [0])
    with pytest.raises(ValueError, match="at_once must be >= 1"):
        train_classifiers([s], 3, SHORT, [0], at_once=0)
