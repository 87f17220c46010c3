"""The object source contract suite."""

from __future__ import annotations

from typing import Any, ClassVar

import numpy as np
import pytest

from tnf.errors import TnfError
from tnf.objects import REFUSE_SIZE, ObjectSource
from tnf.registry import (
    OBJECTS,
)
from tnf.testing.contracts.base import _ComponentContract


# -- object sources ---------------------------------------------------------------------------------
class ObjectSourceContract(_ComponentContract):
    """An object source (``tnf.objects.ObjectSource`` subclass) lists objects and loads them by name.

    Checks: registration and documented Config; config round trip; the source is named as registered and
    lists sorted, unique, non-empty names; each of the first ``max_objects`` objects is either a mesh (metres,
    centred at the origin, a plausible tabletop size, the same on a second load) or, for a source of camera
    images, an existing ``transforms.json``; an unknown name is an error naming it. Override the ``source``
    fixture for a source that needs files (build them with code).
    """

    registry = OBJECTS
    max_objects: ClassVar[int] = 2
    """How many of the source's objects the load test loads."""

    @pytest.fixture(scope="class")
    @classmethod
    def source(cls) -> Any:
        """The object source under test (built once per test class)."""
        return OBJECTS.build(cls.spec())

    def test_is_an_object_source_named_as_registered(self, source):

        assert isinstance(source, ObjectSource)
        assert source.name == self.name, "set the class attribute `name` to the registry name"
        names = source.names()
        assert names and names == sorted(set(names)) and all(isinstance(n, str) and n for n in names)

    def test_objects_load_as_the_contract_says(self, source):

        for name in source.names()[: self.max_objects]:
            views = source.views(name)
            if views is not None:
                assert views.is_file(), f"{name}: views() gives {views}, which is not a file"
                continue
            mesh = source.load(name)
            v = np.asarray(mesh.vertices)
            assert len(mesh.faces) > 0 and np.isfinite(v).all(), name
            assert np.allclose((v.max(0) + v.min(0)) / 2, 0, atol=1e-6), f"{name} is not centred"
            assert REFUSE_SIZE[0] <= float((v.max(0) - v.min(0)).max()) <= REFUSE_SIZE[1], name
            assert np.array_equal(np.asarray(source.load(name).vertices), v), f"{name} loads differently twice"

    def test_unknown_name_is_an_error_naming_it(self, source):
        with pytest.raises(TnfError, match="no_such_object"):
            source.load("no_such_object")
