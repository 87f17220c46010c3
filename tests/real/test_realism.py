"""The realism scores against an independent SSIM (scipy's Gaussian filter) and NumPy's MSE."""

import numpy as np
import pytest
from scipy.ndimage import gaussian_filter

from tnf.real import realism, report
from tnf.real.presses import SensorPresses, disk_masks

SIGMA, K1, K2, L = 1.5, 0.01, 0.03, 255.0


def reference_ssim_map(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Per-pixel SSIM ``[H, W]`` of two ``[H, W, 3]`` images, mean over channels: an 11 px Gaussian window
    (radius 5, sigma 1.5) over mirrored borders (d c b | a b c d), float64, the standard formula."""

    def blur(a):
        return gaussian_filter(a, sigma=SIGMA, truncate=5 / SIGMA, mode="mirror")

    c1, c2 = (K1 * L) ** 2, (K2 * L) ** 2
    out = []
    for ch in range(3):
        a, b = x[..., ch].astype(np.float64), y[..., ch].astype(np.float64)
        ma, mb = blur(a), blur(b)
        va, vb, cov = blur(a * a) - ma**2, blur(b * b) - mb**2, blur(a * b) - ma * mb
        out.append(((2 * ma * mb + c1) * (2 * cov + c2)) / ((ma**2 + mb**2 + c1) * (va + vb + c2)))
    return np.mean(out, axis=0)


@pytest.fixture
def images():
    rng = np.random.default_rng(7)
    real = rng.integers(0, 256, size=(3, 40, 56, 3), dtype=np.uint8)
    # Predictions: one independent, one close to the real frame, one equal to it.
    noisy = np.clip(real.astype(int) + rng.integers(-20, 21, size=real.shape), 0, 255).astype(np.uint8)
    pred = np.stack([rng.integers(0, 256, size=(40, 56, 3), dtype=np.uint8), noisy[1], real[2]])
    region = rng.random((3, 40, 56)) < 0.3
    region[:, 0, :] = True  # the border rows, where the mirrored window matters
    region[:, :, -1] = True
    return pred, real, region


def test_reference_ssim_window_is_the_11_pixel_gaussian():
    # scipy's radius is int(truncate * sigma + 0.5) = 5: an 11-tap kernel, normalised.
    impulse = np.zeros(31)
    impulse[15] = 1.0
    k = gaussian_filter(impulse, sigma=SIGMA, truncate=5 / SIGMA, mode="mirror")
    assert np.count_nonzero(k) == 11 and k.sum() == pytest.approx(1.0)
    r = np.arange(-5, 6)
    w = np.exp(-(r**2) / (2 * SIGMA**2))
    assert np.allclose(k[10:21], w / w.sum())


def test_score_matches_an_independent_ssim_and_mse(images):
    pred, real, region = images
    s = realism.score(pred, real, region)
    assert set(s) == set(realism.METRICS) and all(len(v) == 3 for v in s.values())
    for i in range(3):
        ref = reference_ssim_map(pred[i], real[i])
        assert s["ssim_frame"][i] == pytest.approx(float(ref.mean()), abs=1e-6)
        assert s["ssim_region"][i] == pytest.approx(float(ref[region[i]].mean()), abs=1e-6)
        sq = ((pred[i].astype(np.float64) - real[i].astype(np.float64)) ** 2).mean(-1)
        assert s["mse_frame"][i] == pytest.approx(float(np.mean((pred[i].astype(float) - real[i]) ** 2)), rel=1e-12)
        assert s["mse_region"][i] == pytest.approx(float(sq[region[i]].mean()), rel=1e-12)
    # Sanity of the three cases: unrelated < noisy copy < identical (SSIM 1, MSE 0).
    assert s["ssim_frame"][0] < 0.1 < s["ssim_frame"][1] < s["ssim_frame"][2] == pytest.approx(1.0, abs=1e-12)
    assert s["mse_frame"][2] == 0.0 and s["mse_region"][2] == 0.0
    assert s["mse_frame"][1] == pytest.approx(float(np.mean((pred[1].astype(float) - real[1]) ** 2)))
    assert 100 < s["mse_frame"][1] < 20**2


def test_region_score_differs_from_frame_score_where_the_error_is_local():
    rng = np.random.default_rng(1)
    real = rng.integers(40, 200, size=(1, 48, 64, 3), dtype=np.uint8)
    pred = real.copy()
    pred[0, 20:30, 30:40] = 255 - pred[0, 20:30, 30:40]  # wrong only in a small patch
    region = disk_masks((48, 64), np.array([[35.0, 25.0]]), np.array([6.0]))
    s = realism.score(pred, real, region)
    ref = reference_ssim_map(pred[0], real[0])
    assert s["ssim_region"][0] == pytest.approx(float(ref[region[0]].mean()), abs=1e-6)
    assert s["ssim_region"][0] < s["ssim_frame"][0] - 0.2
    assert s["mse_region"][0] > 10 * s["mse_frame"][0]


def test_regions_and_summary():
    sp = SensorPresses(
        background=np.zeros((20, 30, 3), np.uint8),
        frames=np.zeros((2, 20, 30, 3), np.uint8),
        centers=np.array([[10.0, 5.0], [29.0, 19.0]]),
        radii=np.array([2.0, 3.0]),
        depths=np.array([1e-4, 2e-4]),
        indices=[0, 1],
    )
    reg = realism.regions(sp, 1.5)
    rows, cols = np.mgrid[:20, :30]
    assert np.array_equal(reg[0], (cols - 10) ** 2 + (rows - 5) ** 2 <= 3.0**2)
    assert np.array_equal(reg[1], (cols - 29) ** 2 + (rows - 19) ** 2 <= 4.5**2)
    assert reg[0].sum() == 29  # the lattice points within a radius-3 disk


def test_report_means_and_table():
    per = {"a": {m: [1.0, 3.0] for m in report.ALL_METRICS}, "b": {m: [0.5] for m in report.ALL_METRICS}}
    means = report.mean_scores(per)
    assert means == {"a": {m: 2.0 for m in report.ALL_METRICS}, "b": {m: 0.5 for m in report.ALL_METRICS}}
    lines = report.table(means, {"a": 0.002}).splitlines()
    assert lines[2] == "| a | 2.000 | 2 | 2.00 | 2.000 | 2 | 2.0 |"  # milliseconds per frame last
    assert lines[3] == "| b | 0.500 | 0 | 0.50 | 0.500 | 0 |  |"
    assert report.table(means).splitlines()[3] == lines[3]


# -- the native-size crop: scikit-image's SSIM, MSE and the sharpness ratio ---------------------------------


def brute_ssim(a: np.ndarray, b: np.ndarray) -> float:
    """SSIM with a 7 x 7 uniform window, computed window by window: sample (co)variances over each window's 49
    pixels, the mean over every window that fits inside the image, channels averaged."""
    c1, c2 = (K1 * L) ** 2, (K2 * L) ** 2
    h, w = a.shape[:2]
    out = []
    for ch in range(3):
        vals = []
        for r in range(h - 6):
            for c in range(w - 6):
                x = a[r : r + 7, c : c + 7, ch].astype(np.float64).ravel()
                y = b[r : r + 7, c : c + 7, ch].astype(np.float64).ravel()
                vx, vy, cxy = np.var(x, ddof=1), np.var(y, ddof=1), np.cov(x, y)[0, 1]
                mx, my = x.mean(), y.mean()
                vals.append(((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2)))
        out.append(np.mean(vals))
    return float(np.mean(out))


def test_ssim_uniform_matches_a_window_by_window_computation():
    rng = np.random.default_rng(3)
    a = rng.integers(0, 256, size=(17, 21, 3), dtype=np.uint8)
    b = np.clip(a.astype(int) + rng.integers(-40, 41, size=a.shape), 0, 255).astype(np.uint8)
    assert realism.ssim_uniform(a, b) == pytest.approx(brute_ssim(a, b), abs=1e-9)
    assert realism.ssim_uniform(a, a) == pytest.approx(1.0)


def test_crop_score_on_crops_of_four_contact_radii():
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(5)
    real = rng.integers(0, 256, size=(2, 60, 80, 3), dtype=np.uint8)
    soft = np.stack([gaussian_filter(f.astype(float), (2, 2, 0)) for f in real]).round().astype(np.uint8)
    centers, radii = np.array([[40.0, 30.0], [3.0, 57.0]]), np.array([5.0, 5.0])
    boxes = realism.crop_boxes((60, 80), centers, radii)
    assert boxes[0] == (slice(20, 40), slice(30, 50))  # side 4 x 5 px around (column 40, row 30)
    assert boxes[1] == (slice(47, 60), slice(0, 13))  # clipped at the frame's corner
    same = realism.crop_score(real, real, centers, radii)
    assert same["ssim_crop"] == pytest.approx([1, 1]) and same["mse_crop"] == [0, 0]
    assert same["sharpness"] == pytest.approx([1, 1])
    s = realism.crop_score(soft, real, centers, radii)
    assert all(x < 0.6 for x in s["sharpness"])  # a blurred image is less sharp than the frame
    box = boxes[0]
    assert s["mse_crop"][0] == pytest.approx(((soft[0][box].astype(float) - real[0][box]) ** 2).mean())
    with pytest.raises(ValueError, match="differ"):
        realism.crop_score(soft[:, :50], real, centers, radii)


def test_upsample_is_pil_bilinear_and_keeps_full_size_frames():
    from PIL import Image

    f = np.random.default_rng(1).integers(0, 256, size=(1, 6, 8, 3), dtype=np.uint8)
    big = realism.upsample(f, 16, 12)
    expected = np.asarray(Image.fromarray(f[0]).resize((16, 12), Image.Resampling.BILINEAR))
    assert big.shape == (1, 12, 16, 3) and np.array_equal(big[0], expected)
    assert realism.upsample(big, 16, 12) is big
