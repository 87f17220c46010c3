import pytest

from tnf.real.presses import import_taxim


@pytest.fixture(scope="session")
def taxim_presses(tmp_path_factory):
    """The taxim package's GelSight Mini recording imported once as a press folder (read-only for the tests)."""
    return import_taxim("gelsight_mini", tmp_path_factory.mktemp("taxim") / "presses")
