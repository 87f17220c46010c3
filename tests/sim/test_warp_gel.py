"""Physical checks of the warp gel simulator on meshes made by code."""

import numpy as np
import pytest
import trimesh
import warp as wp

from tnf.errors import TnfError
from tnf.registry import SENSORS, SIMULATORS

R = 0.01  # sphere radius, metres


def _sim(device="cpu", **sensor):
    s = SENSORS.build({"name": "digit", **sensor})
    return s, SIMULATORS.build({"name": "warp_gel"}, sensor=s, device=device)


def _above(height):
    """Sensor pose looking down -z with its gel rim plane `height` above the origin."""
    c2w = np.eye(4)
    c2w[2, 3] = height
    return c2w[None]


@pytest.fixture(scope="module")
def sphere():
    return trimesh.creation.icosphere(subdivisions=5, radius=R)


def test_sphere_press_follows_hertz(sphere):
    # Flat gel on a (nearly) half-space: thickness >> contact radius.
    s, sim = _sim(sag=0.0, thickness=1.0, noise_std=0.0)
    e_star = s.effective_modulus
    start = _above(R + 0.022 + 0.005)
    for force in (0.3, 1.0, 3.0):
        out = sim.press(sphere, start, force)
        d = float(out.penetration[0])
        assert out.hit[0] and out.advance[0] == pytest.approx(0.005, abs=2e-5)
        # Force and contact radius within 3 % of Hertz: F = 4/3 E* sqrt(R) d^1.5, a = sqrt(R d).
        assert 4 / 3 * e_star * np.sqrt(R) * d**1.5 == pytest.approx(force, rel=0.03)
        area = out.contact[0].sum() * np.prod(s.pixel_size())
        assert np.sqrt(area / np.pi) == pytest.approx(np.sqrt(R * d), rel=0.03)
        # The gel takes the sphere's shape: deepest indentation = penetration, at the centre.
        assert out.indentation[0].max() == pytest.approx(d, rel=1e-3)


def test_more_force_never_less_indentation(sphere):
    s, sim = _sim(noise_std=0.0)
    start = np.repeat(_above(R + 0.03), 5, axis=0)
    forces = np.array([0.5, 1.0, 2.0, 4.0, 8.0], dtype=np.float32)
    out = sim.press(sphere, start, forces)
    assert np.all(np.diff(out.penetration) > 0)
    assert np.all(np.diff(out.contact.sum((1, 2))) >= 0)
    assert np.all(np.diff(out.indentation.sum((1, 2))) > 0)
    assert out.force == pytest.approx(forces, rel=1e-4)
    # Smooth fall-off: the gel just outside the contact is pushed in too, less than inside.
    ring = out.indentation[2][~out.contact[2]]
    assert 0 < ring.max() < out.penetration[2]


def test_flat_plate_gives_uniform_indentation():
    s, sim = _sim(sag=0.0, noise_std=0.0)
    plate = trimesh.creation.box(extents=(0.1, 0.1, 0.01))
    out = sim.press(plate, _above(0.005 + 0.022 + 0.004), 5.0)
    gel = s.gel_mask()
    u = out.indentation[0][gel]
    assert out.contact[0][gel].all()
    assert u.std() < 1e-3 * u.mean() and u.mean() == pytest.approx(out.penetration[0], rel=1e-3)
    # Uniform indentation of a flat gel changes no normal: the image is the background (plus noise).
    assert np.abs(out.images[0].astype(int) - sim.background).max() <= 1


def test_no_contact_gives_background_plus_noise(sphere):
    s, sim = _sim(noise_std=3.0)
    c2w = _above(0.1)[0]
    c2w[0, 3] = 0.05  # beside the sphere: every ray misses
    out = sim.press(sphere, c2w[None], 2.0)
    assert not out.hit[0] and out.penetration[0] == 0 and not out.contact.any()
    diff = out.images[0].astype(float) - sim.background
    assert abs(diff.mean()) < 0.2 and diff.std() == pytest.approx(3.0, rel=0.1)


def test_ball_image_colours_follow_slope(sphere):
    s, sim = _sim(noise_std=0.0)
    out = sim.press(sphere, _above(R + 0.03), 3.0)
    diff = out.images[0].astype(float) - sim.background
    assert np.abs(diff).max() > 40  # a clear imprint
    rows, cols = np.nonzero(out.contact[0])
    r0, c0 = int(rows.mean()), int(cols.mean())
    rad = int(np.sqrt(len(rows) / np.pi))
    # Red LED upper right, green upper left: opposite slopes of the dent light up different channels.
    right = diff[r0 - rad // 2 : r0, c0 : c0 + rad]
    left = diff[r0 - rad // 2 : r0, c0 - rad : c0]
    assert (right[..., 0] - right[..., 1]).mean() * (left[..., 0] - left[..., 1]).mean() < 0


@pytest.mark.skipif(not wp.is_cuda_available(), reason="needs a CUDA GPU")
def test_cpu_and_cuda_agree(sphere):
    start = np.repeat(_above(R + 0.03), 3, axis=0)
    start[1, 0, 3] = 0.003
    start[2, 1, 3] = -0.004
    outs = [_sim(device, noise_std=0.0)[1].press(sphere, start, 2.0) for device in ("cpu", "cuda:0")]
    a, b = outs
    assert a.penetration == pytest.approx(b.penetration, rel=1e-3, abs=1e-7)
    assert np.abs(a.indentation - b.indentation).max() < 1e-6
    assert np.abs(a.images.astype(int) - b.images).max() <= 2
    assert (a.contact != b.contact).mean() < 1e-3


def test_mirrored_object_gives_the_mirrored_image():
    # The Digit's mirror symmetry (Sensor.mirror_channels) holds in the simulator: pressing the mirror image
    # of an asymmetric object gives the image flipped left-right with red and green swapped.
    s, sim = _sim(noise_std=0.0)
    ball = trimesh.creation.icosphere(subdivisions=4, radius=0.008)
    ball.apply_translation([0.004, 0.003, 0.0])
    bar = trimesh.creation.box(extents=(0.01, 0.004, 0.02))
    bar.apply_transform(trimesh.transformations.rotation_matrix(0.5, [0, 0, 1]))
    bar.apply_translation([-0.003, -0.004, 0.003])
    obj = trimesh.util.concatenate([ball, bar])
    mirror = obj.copy()
    mirror.apply_transform(np.diag([-1.0, 1.0, 1.0, 1.0]))
    start = _above(0.05)
    out, out_m = sim.press(obj, start, 3.0), sim.press(mirror, start, 3.0)
    assert out.penetration[0] == pytest.approx(out_m.penetration[0], rel=1e-4)
    diff = out.images[0].astype(float) - sim.background
    diff_m = out_m.images[0].astype(float) - sim.background
    order = list(s.mirror_channels())
    energy = np.abs(diff).mean()
    assert energy > 3  # the press changes the image
    # Within 2 % of the imprint's energy (pixels on the contact's rim round either way), while flipping
    # without the channel swap is off by about the energy itself.
    assert np.abs(diff[:, ::-1][..., order] - diff_m).mean() < 0.02 * energy
    assert np.abs(diff[:, ::-1] - diff_m).mean() > 0.5 * energy


def test_press_heights_of_the_ray_cast_gives_the_mesh_press(sphere):
    # The sphere's exact height field under the sensor (gap from each undeformed gel point along -z to the
    # sphere) pressed through press_heights: the same touch as pressing the sphere's mesh from that pose.
    s, sim = _sim(noise_std=0.0, width=60, height=80)
    start = _above(R + 0.022 + 0.005 + 0.004)  # 4 mm in front of the gel's 5 mm bulge
    mesh_touch = sim.press(sphere, start, 3.0)
    p = s.gel_points()
    lateral = p[..., 0] ** 2 + p[..., 1] ** 2
    top = start[0, 2, 3] - np.sqrt(np.clip(R**2 - lateral, 0, None))  # camera-to-sphere-top, along -z
    gaps = np.where(lateral < R**2, top - (-p[..., 2]), np.inf)
    out = sim.press_heights(gaps[None], 3.0)
    assert out.hit[0] and out.penetration[0] == pytest.approx(mesh_touch.penetration[0], rel=1e-3)
    assert out.advance[0] == pytest.approx(mesh_touch.advance[0], abs=1e-5)
    assert (out.contact[0] != mesh_touch.contact[0]).mean() < 0.002
    # The two differ only by the mesh's facets: at most one level anywhere, against a press image that
    # differs from the background by 7.7 levels on average.
    diff = np.abs(out.images[0].astype(int) - mesh_touch.images[0].astype(int))
    assert diff.mean() < 0.05 and diff.max() <= 1
    assert np.abs(mesh_touch.images[0].astype(int) - sim.background.astype(int)).mean() > 5
    # No surface under any pixel: the untouched gel, the background.
    empty = sim.press_heights(np.full((1, 80, 60), np.inf), 3.0)
    assert not empty.hit[0] and np.array_equal(empty.images[0], sim.background)
    with pytest.raises(TnfError, match=r"gaps must be \[B, 80, 60\]"):
        sim.press_heights(gaps, 3.0)
