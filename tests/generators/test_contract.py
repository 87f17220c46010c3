"""The in-tree generators pass the same contract suite as plugin generators (tiny networks)."""

from tnf.testing import GeneratorContract


class TestTNcGANContract(GeneratorContract):
    name = "tn_cgan"
    params = {"ngf": 4, "ndf": 4}


class TestLeeContract(GeneratorContract):
    name = "lee"
    params = {"ngf": 4, "ndf": 4}


class TestCycleGANContract(GeneratorContract):
    name = "cyclegan"
    params = {"ngf": 4, "ndf": 4, "n_blocks": 1, "pool_size": 2}
