"""Generator architectures: shapes, skip connections, configs, one optimisation step, a tiny overfit."""

import random

import pytest
import torch
import torch.nn.functional as F

from tests.generators.synthetic import make_pairs
from tnf import metrics
from tnf.errors import TnfError
from tnf.generators import PlainOptimisation
from tnf.generators.nets.gan import NoiseDropout
from tnf.generators.nets.resnet import ImagePool
from tnf.registry import GENERATORS

TINY = {
    "tn_cgan": {"ngf": 4, "ndf": 4},
    "lee": {"ngf": 4, "ndf": 4},
    "cyclegan": {"ngf": 4, "ndf": 4, "n_blocks": 2},
}


def build(name, **kw):
    return GENERATORS.build({"name": name, **TINY[name], **kw})


def test_registered():
    assert {"tn_cgan", "lee", "cyclegan"} <= set(GENERATORS.names())


@pytest.mark.parametrize("name", ["tn_cgan", "lee", "cyclegan"])
@pytest.mark.parametrize("size", [32, 128])
def test_output_shape_and_range(name, size):
    torch.manual_seed(0)
    g = build(name, image_size=size).eval()
    batch = make_pairs(2, size)
    with torch.no_grad():
        out = g.generate(batch)
    assert out.shape == (2, 3, size, size)
    assert out.dtype == torch.float32
    assert out.abs().max() <= 1.0 and torch.isfinite(out).all()


def test_tn_cgan_default_architecture():
    g = GENERATORS.build({"name": "tn_cgan"})
    # One encoder per input, each down to 1 x 1 at 128 px (7 stride-2 levels).
    assert set(g.net_g.encoders) == {"rgb", "depth_and_slope", "background"}
    assert all(len(e.blocks) == 7 for e in g.net_g.encoders.values())
    assert g.net_g.encoders["depth_and_slope"].blocks[0].in_channels == 3  # the depth image and its two slopes
    # Skips from the background and depth encoders; no dropout (deterministic generation).
    assert g.net_g.skips == ("background", "depth_and_slope")
    assert not [m for m in g.net_g.decoder.modules() if isinstance(m, NoiseDropout)]
    # The paper's layout: dropout 0.5 in the three innermost decoder blocks, on when generating.
    paper_layout = {"inputs": ["rgb", "depth", "background"], "skips": ["background"], "dropout": 0.5}
    paper = GENERATORS.build({"name": "tn_cgan", **paper_layout})
    assert paper.net_g.encoders["depth"].blocks[0].in_channels == 1
    drops = [m for m in paper.net_g.decoder.modules() if isinstance(m, NoiseDropout)]
    assert len(drops) == 3 and all(d.p == 0.5 and d.always_on for d in drops)
    # PatchGAN on condition (3 + 3 + 3) + tactile (3) channels: 14 x 14 logits for 128 px.
    assert g.net_d.net[0].in_channels == 12
    assert g.net_d(torch.zeros(1, 12, 128, 128)).shape == (1, 1, 14, 14)
    assert g.cfg.lambda_l1 == 100 and g.cfg.lr == 2e-4 and g.cfg.beta1 == 0.5
    # A full-resolution head and an SSIM loss term (the paper: neither).
    assert g.net_g.head is not None and g.cfg.lambda_ssim == 60


@pytest.mark.parametrize("skips", [["background"], ["background", "depth_and_slope"]])
def test_tn_cgan_skips_come_from_the_named_encoders(skips):
    from tnf.generators.nets.conditioning import conditions

    torch.manual_seed(0)
    g = build("tn_cgan", image_size=32, skips=skips).eval()
    batch = make_pairs(2, 32)
    feats = {k: g.net_g.encoders[k](v) for k, v in conditions(batch, g.inputs).items()}
    seen = []
    hooks = [b.register_forward_pre_hook(lambda m, i: seen.append(i[0].clone())) for b in g.net_g.decoder.blocks]
    with torch.no_grad():
        g.net_g.encoders.eval()
        g.generate(batch)
    for h in hooks:
        h.remove()
    # Bottleneck = concatenated innermost features of the three encoders.
    assert torch.equal(seen[0], torch.cat([feats[k][-1] for k in ("rgb", "depth_and_slope", "background")], 1))
    # Every later block's input ends with the named encoders' features at that scale, in the order named.
    n = len(seen)
    for k in range(1, n):
        f = torch.cat([feats[s][n - 1 - k] for s in skips], 1)
        assert seen[k].shape[-2:] == f.shape[-2:]
        assert torch.equal(seen[k][:, -f.shape[1] :], f)


def test_tn_cgan_inputs_are_configurable():
    g = build("tn_cgan", inputs=["rgb", "background"], skips=["background"], image_size=32)
    assert set(g.net_g.encoders) == {"rgb", "background"}
    assert g.net_d.net[0].in_channels == 9
    batch = make_pairs(2, 32)
    del batch["depth"]
    assert g.generate(batch).shape == (2, 3, 32, 32)
    with pytest.raises(TnfError, match="skips"):
        build("tn_cgan", inputs=["rgb", "depth"])  # a default skip (background) is not an input
    with pytest.raises(TnfError, match="needs batch keys"):
        build("tn_cgan", image_size=32).generate({"rgb": batch["rgb"]})


def test_depth_slope_is_the_scaled_clipped_gradient():
    from tnf.generators.nets.conditioning import SLOPE_GAIN, conditions, depth_slope

    cols = torch.arange(16, dtype=torch.float32)
    ramp = (0.002 * cols).expand(1, 1, 16, 16).clone()  # depth rising 0.002 per column, flat down the rows
    slope = depth_slope(ramp)
    assert slope.shape == (1, 2, 16, 16)
    torch.testing.assert_close(slope[0, 0, :, 1:-1], torch.full((16, 14), 0.002 * SLOPE_GAIN))
    torch.testing.assert_close(slope[0, 1], torch.zeros(16, 16))
    assert slope[0, 0, :, 0].mean() == pytest.approx(0.001 * SLOPE_GAIN)  # the replicated edge: half the step
    both = conditions({"depth": ramp}, ("depth_and_slope",))["depth_and_slope"]  # one encoder sees the two
    torch.testing.assert_close(both, torch.cat([ramp, slope], 1))
    step = torch.zeros(1, 1, 8, 8)
    step[..., 4:] = 1.0  # a jump to the far plane clips
    assert depth_slope(step).max() == 1.0


def test_depth_slope_equals_the_padded_central_difference():
    """The one-buffer derivation gives exactly what padding, differencing and concatenating give."""
    from tnf.generators.nets.conditioning import SLOPE_GAIN, depth_and_slope, depth_slope

    torch.manual_seed(0)
    depth = torch.rand(3, 1, 16, 24) * 0.03 - 0.5  # rough relief, non-square ...
    depth[..., 10:, :] += 0.2  # ... with a jump that clips
    padded = F.pad(depth, (1, 1, 1, 1), mode="replicate")
    dx = (padded[..., 1:-1, 2:] - padded[..., 1:-1, :-2]) / 2
    dy = (padded[..., 2:, 1:-1] - padded[..., :-2, 1:-1]) / 2
    reference = (torch.cat([dx, dy], 1) * SLOPE_GAIN).clamp(-1.0, 1.0)
    assert 0 < (reference.abs() == 1).float().mean() < 0.5  # some pixels clip, most do not
    assert torch.equal(depth_slope(depth), reference)
    assert torch.equal(depth_and_slope(depth), torch.cat([depth, reference], 1))


def test_depth_slopes_are_differentiable_and_reject_other_shapes():
    """Gradients reach the depth image through the slopes, as through the padded form; a batch that is not
    [B, 1, H, W] with H, W >= 2 gets a clear error, not an unpacking or narrowing one."""
    from tnf.generators.nets.conditioning import depth_and_slope, depth_slope

    torch.manual_seed(0)
    depth = (torch.rand(2, 1, 8, 8) * 0.01).requires_grad_(True)
    depth_and_slope(depth).square().sum().backward()
    assert depth.grad is not None and depth.grad.abs().sum() > 0
    padded = F.pad(depth.detach(), (1, 1, 1, 1), mode="replicate").requires_grad_(True)
    ref = (padded[..., 1:-1, 2:] - padded[..., 1:-1, :-2]) / 2 * 64.0
    ref_d = torch.autograd.grad(ref.square().sum(), padded)[0]
    mine = depth.detach().clone().requires_grad_(True)
    got_d = torch.autograd.grad(depth_slope(mine)[:, :1].square().sum(), mine)[0]
    # The replicated border's gradient folds back onto the edge pixels.
    folded = ref_d[..., 1:-1, 1:-1].clone()
    folded[..., :, 0] += ref_d[..., 1:-1, 0]
    folded[..., :, -1] += ref_d[..., 1:-1, -1]
    assert torch.allclose(got_d, folded, atol=1e-6)
    for bad in (torch.rand(2, 8, 8), torch.rand(2, 3, 8, 8), torch.rand(2, 1, 1, 8)):
        with pytest.raises(TnfError, match=r"\[B, 1, H, W\]"):
            depth_slope(bad)


@pytest.mark.parametrize("name", ["tn_cgan", "lee"])
@pytest.mark.parametrize(
    "inputs", [["rgb", "depth", "background", "depth_slope"], ["rgb", "depth_and_slope", "background"]]
)
def test_depth_slope_input_trains_from_the_depth_image(name, inputs):
    torch.manual_seed(0)
    derived = inputs[-1] if "depth_slope" in inputs else inputs[1]
    skips = {"skips": ["background", derived]} if name == "tn_cgan" else {}
    g = build(name, image_size=32, inputs=inputs, **skips)
    assert derived in g.net_g.encoders
    batch = make_pairs(4, 32)  # no derived key: it is made from depth
    assert g.generate(batch).shape == (4, 3, 32, 32)
    before = _l1(g, batch)
    g.training_step(batch, PlainOptimisation(g))
    assert _l1(g, batch) < before
    del batch["depth"]
    with pytest.raises(TnfError, match="needs batch keys"):
        g.generate(batch)


def test_bad_configs_are_errors():
    with pytest.raises(TnfError, match="image_size"):
        build("tn_cgan", image_size=100)
    with pytest.raises(TnfError, match="norm"):
        build("lee", norm="group")
    with pytest.raises(TnfError, match="unknown key"):
        build("cyclegan", n_block=3)


def test_dropout_at_generation_makes_outputs_stochastic():
    torch.manual_seed(0)
    g = build("tn_cgan", image_size=32, dropout=0.5).eval()
    batch = make_pairs(2, 32)
    with torch.no_grad():
        assert not torch.equal(g.generate(batch), g.generate(batch))
    g = build("tn_cgan", image_size=32, dropout=0.5, dropout_at_generation=False).eval()
    with torch.no_grad():
        assert torch.equal(g.generate(batch), g.generate(batch))


def test_lee_architecture():
    g = build("lee", image_size=32)
    convs = [m for m in g.net_g.modules() if isinstance(m, (torch.nn.Conv2d, torch.nn.ConvTranspose2d))]
    assert all(c.kernel_size == (5, 5) and c.stride == (2, 2) for c in convs)
    assert list(g.net_g.encoders) == ["rgb"] and g.net_g.skips == ("rgb",)
    d_convs = [m for m in g.net_d.modules() if isinstance(m, torch.nn.Conv2d)]
    assert len(d_convs) == 4 and isinstance(g.net_d.fc, torch.nn.Linear)
    assert g.net_d(torch.zeros(3, 6, 32, 32)).shape == (3, 1)
    assert g.cfg.lambda_l1 == 0
    assert all(isinstance(o, torch.optim.RMSprop) for o in g.configure_optimizers())


def test_cyclegan_architecture():
    from tnf.generators.nets.resnet import ResnetBlock

    g = GENERATORS.build({"name": "cyclegan"})
    assert sum(isinstance(m, ResnetBlock) for m in g.net_g.modules()) == 6
    assert g.cfg.lambda_cycle == 10 and g.cfg.lambda_identity == 0.5 and g.cfg.pool_size == 50
    assert g.pool_tactile.size == 50


def _l1(g, batch):
    with torch.no_grad():
        return (g.generate(batch) - batch["tactile"]).abs().mean().item()


@pytest.mark.parametrize(
    "name,kw",
    [
        ("tn_cgan", {"norm": "instance", "dropout": 0.0, "lambda_gan": 1.0}),
        ("lee", {"norm": "instance", "dropout": 0.0, "lambda_l1": 100.0}),
    ],
)
def test_one_step_lowers_l1(name, kw):
    torch.manual_seed(0)
    g = build(name, image_size=32, **kw)
    batch = make_pairs(4, 32)
    opt = PlainOptimisation(g)
    before = _l1(g, batch)
    losses = g.training_step(batch, opt)
    assert {"loss_g", "loss_d", "d_real", "d_fake"} <= set(losses)
    assert all(torch.isfinite(v) for v in losses.values())
    assert _l1(g, batch) < before


def test_cyclegan_step_lowers_cycle_loss():
    torch.manual_seed(0)
    g = build("cyclegan", image_size=32)
    batch = make_pairs(4, 32)

    def cycle():
        with torch.no_grad():
            return (g.net_f(g.net_g(batch["rgb"])) - batch["rgb"]).abs().mean().item()

    opt = PlainOptimisation(g)
    before = cycle()
    losses = g.training_step(batch, opt)
    assert cycle() < before
    assert {"loss_cycle", "loss_idt", "loss_d"} <= set(losses)
    assert g.pool_tactile.filled == 4  # the pool filled with this step's fakes


class LoopPool:
    """The image pool as written image by image (pix2pix's reference code): what ImagePool must return."""

    def __init__(self, size):
        self.size, self.images = size, []

    def query(self, images):
        out = []
        for img in images.detach():
            img = img.unsqueeze(0)
            if len(self.images) < self.size:
                self.images.append(img)
                out.append(img)
            elif random.random() > 0.5:
                i = random.randrange(self.size)
                out.append(self.images[i].clone())
                self.images[i] = img
            else:
                out.append(img)
        return torch.cat(out, 0)


@pytest.mark.parametrize("size", [3, 50])
def test_image_pool_returns_what_the_image_by_image_pool_returns(size):
    # Batches smaller and larger than the pool; with 40 images against 3 slots, some slot is drawn twice in one
    # batch, and the second draw must return the image the first one stored.
    batches = [torch.randn(n, 3, 8, 8) for n in (2, 5, 40, 1, 16)]
    ours, reference = ImagePool(size), LoopPool(size)
    random.seed(7)
    got = [ours.query(b) for b in batches]
    state = random.getstate()
    random.seed(7)
    want = [reference.query(b) for b in batches]
    assert random.getstate() == state  # the same draws, so training runs stay as they were
    for g, w in zip(got, want, strict=True):
        assert torch.equal(g, w)
    assert torch.equal(ours.images, torch.cat(reference.images))
    x = torch.randn(4, 3, 8, 8)
    assert ImagePool(0).query(x) is x


@pytest.mark.parametrize("residual", [False, True])
def test_tn_cgan_overfits_a_handful_of_pairs(residual):
    torch.manual_seed(0)
    g = build("tn_cgan", image_size=16, ngf=16, ndf=8, d_layers=2, dropout=0.0, lr=2e-3, residual=residual)
    batch = make_pairs(4, 16)
    opt = PlainOptimisation(g)
    with torch.no_grad():
        start = metrics.ssim(g.eval().generate(batch), batch["tactile"]).mean().item()
    g.train()
    for _ in range(100):
        g.training_step(batch, opt)
    g.eval()
    with torch.no_grad():
        s = metrics.ssim(g.generate(batch), batch["tactile"]).mean().item()
    # Far better than predicting the background (where a residual network starts) and than the untrained
    # network: the blobs were learnt.
    bg = metrics.ssim(batch["background"], batch["tactile"]).mean().item()
    assert s > 0.98 and s > bg + 0.02, (start, bg, s)
    assert abs(start - bg) < 0.01 if residual else s > start + 0.2, (start, bg, s)


@pytest.mark.parametrize("norm", ["batch", "none"])
@pytest.mark.parametrize("training", [True, False])
def test_tn_cgan_full_res_head_sees_the_skip_images(norm, training):
    from tnf.generators.nets.conditioning import conditions

    torch.manual_seed(0)
    g = build("tn_cgan", image_size=32, full_res_head=True, norm=norm).train(training)
    batch = make_pairs(2, 32)
    cond = conditions(batch, g.inputs)
    decoded = []
    hook = g.net_g.decoder.register_forward_hook(lambda m, i, o: decoded.append(o.clone()))
    out = g.net_g(cond)
    hook.remove()
    # The head works on the decoder's ngf (4) full-resolution features followed by the background image and the
    # depth image with its slopes, in the order of skips; it splits its first convolution instead of
    # concatenating them.
    assert decoded[0].shape == (2, 4, 32, 32)
    head_in = torch.cat([decoded[0], batch["background"], cond["depth_and_slope"]], 1)
    expected = batch["background"] + g.net_g.head(head_in)
    if not training:
        expected = expected.clamp(-1, 1)
    assert torch.allclose(out, expected, atol=1e-5)
    # The images reach the output through the head, not only through their encoders.
    with torch.no_grad():
        w = g.net_g.head[1].weight
        w[:, 4:] = 0
        assert not torch.allclose(g.net_g(cond), out, atol=1e-4)
    assert build("tn_cgan", image_size=32, full_res_head=False).net_g.head is None
    # Without skips the head sees the decoder's features alone.
    g = build("tn_cgan", image_size=32, full_res_head=True, skips=[]).eval()
    assert g.net_g.head[1].in_channels == 4 and g.generate(batch).shape == (2, 3, 32, 32)


@pytest.mark.parametrize("full_res_head", [True, False])
def test_tn_cgan_residual_adds_to_the_background(full_res_head):
    torch.manual_seed(0)
    g = build("tn_cgan", image_size=32, residual=True, full_res_head=full_res_head)
    last = [m for m in g.net_g.modules() if isinstance(m, (torch.nn.Conv2d, torch.nn.ConvTranspose2d))][-1]
    batch = make_pairs(2, 32)
    raw = []
    hook = last.register_forward_hook(lambda m, i, o: raw.append(o.clone()))
    with torch.no_grad():
        trained = g.train().generate(batch)
        out = g.eval().generate(batch)
    hook.remove()
    # Training sees background + the last layer's output, unclipped; generating clips the same sum to [-1, 1].
    assert torch.allclose(trained, batch["background"] + raw[0], atol=1e-6)
    assert torch.allclose(out, (batch["background"] + raw[1]).clamp(-1, 1), atol=1e-6)
    assert out.abs().max() <= 1 and not torch.equal(out, batch["background"])
    # A last layer that outputs nothing leaves the background as it is.
    with torch.no_grad():
        last.weight.zero_()
        last.bias.zero_()
        assert torch.equal(g.generate(batch), batch["background"])
    with pytest.raises(TnfError, match="must include background"):
        build("tn_cgan", residual=True, inputs=["rgb", "depth"], skips=["depth"])


def test_tn_cgan_ssim_loss_term():
    torch.manual_seed(0)
    g = build("tn_cgan", image_size=32, lambda_ssim=10.0)
    batch = make_pairs(4, 32)
    losses = g.training_step(batch, PlainOptimisation(g))
    assert 0 < losses["loss_ssim"] < 1
    # The unquantised SSIM the loss uses is the evaluation's SSIM (128 px) once the images are 8-bit values.
    a, b = (torch.randint(0, 256, (2, 3, 128, 128)).float() / 127.5 - 1 for _ in range(2))
    b = (a + 0.3 * b).clamp(-1, 1).mul(127.5).round().div(127.5)
    assert torch.allclose(metrics.ssim_unquantised(a, b), metrics.ssim(a, b), atol=1e-4)
    with pytest.raises(TnfError, match="loss weights"):
        build("tn_cgan", lambda_ssim=-1.0)


def test_tn_cgan_reports_d_outputs_on_its_loss_scale():
    """d_real / d_fake (what the discriminator watch reads) are on the scale the loss drives to 1 and 0: sigmoid
    probabilities for the vanilla loss, the raw outputs for LSGAN (whose sigmoid would never pass 0.73)."""
    from tnf.generators.callbacks import DiscriminatorWatch, discriminator_saturated
    from tnf.generators.nets.gan import d_output

    t = DiscriminatorWatch.Config().threshold

    won_real, won_fake = torch.full((2, 1, 4, 4), 1.0), torch.full((2, 1, 4, 4), 0.0)
    assert d_output(won_real, "lsgan").item() == pytest.approx(1.0)
    assert discriminator_saturated(d_output(won_real, "lsgan").item(), d_output(won_fake, "lsgan").item(), t)
    assert d_output(torch.full((2, 1, 4, 4), 6.0), "vanilla").item() == pytest.approx(
        torch.sigmoid(torch.tensor(6.0)).item()
    )
    assert not discriminator_saturated(d_output(won_real, "vanilla").item(), d_output(won_fake, "vanilla").item(), t)
    # One real training step reports them under either loss.
    torch.manual_seed(0)
    for mode in ("vanilla", "lsgan"):
        g = build("tn_cgan", image_size=16, ngf=4, ndf=4, d_layers=2, gan_mode=mode, lambda_gan=1.0)
        out = g.training_step(make_pairs(2, 16), PlainOptimisation(g))
        assert out["d_real"].shape == () and torch.isfinite(out["d_real"]) and torch.isfinite(out["d_fake"])


def test_tn_cgan_lambda_gan_weighs_the_adversarial_term():
    """The generator's loss is lambda_gan x cGAN + lambda_l1 x L1 + lambda_ssim x (1 - SSIM); with lambda_gan 0
    the discriminator has no optimiser and is never run, and the generator still learns from L1 and SSIM."""
    batch = make_pairs(4, 32)
    torch.manual_seed(0)
    g = build("tn_cgan", image_size=32, lambda_gan=0.25)
    out = g.training_step(batch, PlainOptimisation(g))
    expected = 0.25 * out["loss_g_gan"] + 100.0 * out["loss_l1"] + 60.0 * out["loss_ssim"]
    assert out["loss_g"].item() == pytest.approx(expected.item(), rel=1e-5)

    torch.manual_seed(0)
    g = build("tn_cgan", image_size=32, lambda_gan=0.0)
    d0 = [p.detach().clone() for p in g.net_d.parameters()]
    g0 = [p.detach().clone() for p in g.net_g.parameters()]
    opt = PlainOptimisation(g)
    assert len(opt.optimizers()) == 1
    losses = [g.training_step(batch, opt) for _ in range(3)]
    assert not {"d_real", "d_fake", "loss_d", "loss_g_gan"} & set(losses[0])
    assert all(torch.equal(a, b) for a, b in zip(d0, g.net_d.parameters()))
    assert any(not torch.equal(a, b) for a, b in zip(g0, g.net_g.parameters()))
    assert losses[-1]["loss_l1"] < losses[0]["loss_l1"]
    for out in losses:
        assert out["loss_g"].item() == pytest.approx(
            (100.0 * out["loss_l1"] + 60.0 * out["loss_ssim"]).item(), rel=1e-5
        )
    with pytest.raises(TnfError, match="no loss"):
        build("tn_cgan", lambda_gan=0.0, lambda_l1=0.0, lambda_ssim=0.0)
    with pytest.raises(TnfError, match="lambda_gan=-1"):
        build("tn_cgan", lambda_gan=-1.0)


def test_tn_cgan_gan_press_margin_keeps_the_adversarial_gradient_on_the_press():
    """press_mask marks where the real image leaves the background, grown by the margin; press_only keeps the
    image's values and passes gradient only there; a training step with a margin trains both networks."""
    from tnf.generators.tn_cgan import PRESS_LEVELS, press_mask, press_only

    bg = torch.zeros(1, 3, 32, 32)
    real = bg.clone()
    real[:, 1, 10:14, 20:22] = 2 * (PRESS_LEVELS + 5) / 255  # a press, in one channel
    real[:, 0, 0:2, 0:2] = 2 * (PRESS_LEVELS - 5) / 255  # a change below the threshold: not a press
    inside = torch.zeros(1, 1, 32, 32, dtype=torch.bool)
    inside[..., 10:14, 20:22] = True
    assert torch.equal(press_mask(real, bg, 0).bool(), inside)
    grown = press_mask(real, bg, 3).bool()
    assert grown[..., 7:17, 17:25].all() and grown.sum() == 10 * 8

    fake = torch.randn(1, 3, 32, 32, requires_grad=True)
    shaped = press_only(fake, real, bg, 3)
    assert torch.equal(shaped, fake)
    shaped.sum().backward()
    assert torch.equal(fake.grad != 0, grown.expand(1, 3, 32, 32))

    torch.manual_seed(0)
    g = build("tn_cgan", image_size=32, lambda_gan=1.0, gan_press_margin=4)
    d0 = [p.detach().clone() for p in g.net_d.parameters()]
    out = g.training_step(make_pairs(4, 32), PlainOptimisation(g))
    assert torch.isfinite(out["loss_g_gan"]) and out["loss_g_gan"] > 0
    assert any(not torch.equal(a, b) for a, b in zip(d0, g.net_d.parameters()))
    with pytest.raises(TnfError, match="gan_press_margin must be -1"):
        build("tn_cgan", lambda_gan=1.0, gan_press_margin=-2)
    with pytest.raises(TnfError, match="finds the press against the background"):
        build("tn_cgan", inputs=["rgb", "depth"], skips=["depth"], residual=False, lambda_gan=1.0, gan_press_margin=2)
    with pytest.raises(TnfError, match="lambda_gan=0 turns off"):
        build("tn_cgan", lambda_gan=0.0, gan_press_margin=2)


def test_tn_cgan_coords_append_the_pixel_position():
    from tnf.generators.nets.conditioning import conditions, coordinate_grid

    grid = coordinate_grid(4)
    assert grid.shape == (1, 2, 4, 4)
    centres = torch.tensor([-0.75, -0.25, 0.25, 0.75])
    assert torch.equal(grid[0, 0], centres.expand(4, 4))  # x along the width
    assert torch.equal(grid[0, 1], centres[:, None].expand(4, 4))  # y down the rows

    torch.manual_seed(0)
    g = build("tn_cgan", image_size=32, coords=["depth_and_slope"]).eval()
    enc = g.net_g.encoders
    assert enc["depth_and_slope"].blocks[0].in_channels == 5 and enc["rgb"].blocks[0].in_channels == 3
    assert g.net_g.head[1].in_channels == 4 + 3 + 5  # features, background, depth with slopes and position
    # The position channels are made again from the image size, not checkpointed.
    assert "net_g.position_grid" in dict(g.named_buffers()) and "net_g.position_grid" not in g.state_dict()
    batch = make_pairs(2, 32)
    seen = []
    hook = enc["depth_and_slope"].register_forward_pre_hook(lambda m, i: seen.append(i[0].clone()))
    with torch.no_grad():
        g.generate(batch)
    hook.remove()
    cond = conditions(batch, g.inputs)["depth_and_slope"]
    assert torch.equal(seen[0][:, :3], cond)
    assert torch.equal(seen[0][:, 3:], coordinate_grid(32).expand(2, -1, -1, -1))
    with pytest.raises(TnfError, match="coords"):
        build("tn_cgan", coords=["depth"])  # not an input


def test_tn_cgan_with_coords_trains():
    torch.manual_seed(0)
    g = build("tn_cgan", image_size=32, coords=["depth_and_slope", "background"])
    batch = make_pairs(4, 32)
    before = _l1(g, batch)
    g.training_step(batch, PlainOptimisation(g))
    assert _l1(g, batch) < before
    # Without coords (the default, and every configuration saved before the option) the layout is as before.
    plain = build("tn_cgan", image_size=32)
    assert plain.cfg.coords == [] and plain.net_g.encoders["depth_and_slope"].blocks[0].in_channels == 3


def test_compiled_networks_compute_the_eager_losses_and_gradients_in_fp32():
    # train.compile: CycleGAN's training step with its networks through torch.compile computes the eager step's
    # losses and gradients to float tolerance, and the state dict keeps its keys. At lr 0 the weights stay put, so
    # every step compares the same computation (with lr > 0 the runs part: Adam moves each weight whose gradient
    # is only rounding noise, such as a bias before an instance norm, by a whole learning rate either way).
    import copy

    from tnf.generators.system import compile_networks

    torch.manual_seed(0)
    eager = build("cyclegan", image_size=32, lr=0.0)
    compiled = copy.deepcopy(eager)
    compile_networks(compiled)
    assert list(compiled.state_dict()) == list(eager.state_dict())
    batch = make_pairs(4, 32)
    losses = []
    for g in (eager, compiled):
        random.seed(0)
        opt = PlainOptimisation(g)
        losses.append([g.training_step(batch, opt) for _ in range(2)])
    for step_eager, step_compiled in zip(*losses, strict=True):
        for key, value in step_eager.items():
            torch.testing.assert_close(step_compiled[key], value, rtol=1e-5, atol=1e-6, msg=key)
    # Each parameter's gradient, as a whole: 1e-4 of its norm, plus 1e-4 for those whose gradient is rounding noise.
    for (name, p), q in zip(eager.named_parameters(), compiled.parameters(), strict=True):
        assert (q.grad - p.grad).norm() <= 1e-4 * p.grad.norm() + 1e-4, name
