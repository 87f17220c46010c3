import numpy as np
import pytest

from tnf.errors import TnfError
from tnf.sim.touch import sphere_directions

AXIS = [1.0, 0.0, 0.0]


def test_held_out_cone_splits_the_sphere():
    rng = np.random.default_rng(0)
    cos30 = np.cos(np.radians(30))
    inside = sphere_directions(rng, 500, AXIS, 30.0, inside=True)
    outside = sphere_directions(rng, 500, AXIS, 30.0, inside=False)
    assert inside.shape == outside.shape == (500, 3)
    assert np.allclose(np.linalg.norm(inside, axis=1), 1) and np.allclose(np.linalg.norm(outside, axis=1), 1)
    assert (inside[:, 0] >= cos30).all() and (outside[:, 0] < cos30).all()


@pytest.mark.parametrize("inside", [True, False])
def test_no_cone_draws_every_split_from_the_whole_sphere(inside):
    # cone 0 is the paper's protocol: novel-view touches drawn like the training touches.
    v = sphere_directions(np.random.default_rng(1), 4000, AXIS, 0.0, inside=inside)
    assert v.shape == (4000, 3)
    # Uniform on the sphere: the share within 30 degrees of the axis is (1 - cos 30) / 2, about 6.7 %,
    # and the mean direction is near the centre.
    share = (v[:, 0] >= np.cos(np.radians(30))).mean()
    assert 0.05 < share < 0.085
    assert np.abs(v.mean(0)).max() < 0.05


@pytest.mark.parametrize("cone", [-5.0, 180.0])
def test_cone_outside_its_range_is_refused(cone):
    with pytest.raises(TnfError, match="half-angle"):
        sphere_directions(np.random.default_rng(0), 10, AXIS, cone, inside=True)


def test_lateral_offset_moves_each_start_pose_sideways_within_the_box():
    from tnf.sim.touch import start_poses

    dirs = sphere_directions(np.random.default_rng(2), 400, AXIS, 0.0, inside=True)
    centred = start_poses(np.random.default_rng(3), dirs, 0.15)
    rng = np.random.default_rng(3)
    moved = start_poses(rng, dirs, 0.15, lateral=(0.004, 0.002))
    # Only the position changes, and only within the sensor's own image plane.
    assert np.allclose(moved[:, :3, :3], centred[:, :3, :3])
    step = moved[:, :3, 3] - centred[:, :3, 3]
    local = np.einsum("nji,nj->ni", centred[:, :3, :3], step)  # the step in each sensor's frame
    assert np.allclose(local[:, 2], 0.0, atol=1e-12)
    assert (np.abs(local[:, 0]) <= 0.004).all() and (np.abs(local[:, 1]) <= 0.002).all()
    # Uniform over the box: the draws reach near its edges on both sides.
    assert local[:, 0].min() < -0.0035 and local[:, 0].max() > 0.0035
    assert local[:, 1].min() < -0.00175 and local[:, 1].max() > 0.00175
    # No spread draws nothing: the poses and the generator's state are those of the plain call.
    plain_rng = np.random.default_rng(3)
    again = start_poses(plain_rng, dirs, 0.15, lateral=(0.0, 0.0))
    assert np.array_equal(again, centred) and plain_rng.uniform() == np.random.default_rng(3).uniform()
