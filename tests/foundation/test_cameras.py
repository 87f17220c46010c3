"""tnf.cameras.look_at: a rigid pose looking at the target, and its two documented fallbacks near ``up``."""

import numpy as np
import pytest

from tnf.cameras import look_at
from tnf.errors import TnfError


@pytest.mark.parametrize("fallback", ["cone", "parallel"])
def test_look_at_is_a_rotation_looking_at_the_target(fallback):
    rng = np.random.default_rng(0)
    for _ in range(50):
        eye, target = rng.normal(size=3), rng.normal(size=3) * 0.1
        m = look_at(eye, target, fallback=fallback)
        r = m[:3, :3]
        np.testing.assert_allclose(r.T @ r, np.eye(3), atol=1e-12)
        assert np.linalg.det(r) > 0
        view = (target - eye) / np.linalg.norm(target - eye)
        np.testing.assert_allclose(-m[:3, 2], view, atol=1e-12)
        np.testing.assert_array_equal(m[:3, 3], eye)
        assert m[:3, 0] @ [0.0, 0.0, 1.0] == pytest.approx(0.0, abs=1e-12)  # no roll: right is horizontal


def test_fallbacks_differ_only_close_to_up():
    one_degree = np.array([np.sin(np.radians(1.0)), 0.0, np.cos(np.radians(1.0))])
    cone, parallel = look_at(one_degree), look_at(one_degree, fallback="parallel")
    assert abs(cone[:3, 0] @ [0.0, 1.0, 0.0]) < 1e-12  # +y is up: right has no y
    assert abs(parallel[:3, 0] @ [0.0, 0.0, 1.0]) < 1e-12  # +z is still up
    overhead = np.array([0.0, 0.0, 1.0])
    np.testing.assert_array_equal(look_at(overhead), look_at(overhead, fallback="parallel"))
    far = np.array([1.0, 0.5, 0.3])
    np.testing.assert_array_equal(look_at(far), look_at(far, fallback="parallel"))


def test_unknown_fallback_is_refused():
    with pytest.raises(TnfError, match="fallback"):
        look_at([1.0, 0.0, 0.0], fallback="nearest")  # type: ignore[arg-type]
