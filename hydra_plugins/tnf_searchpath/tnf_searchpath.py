"""Hydra search-path plugin: config packages that plugins register under the ``tnf.conf`` entry point.

A plugin declares ``[project.entry-points."tnf.conf"] NAME = "its_package.conf"``; the YAML files in that
package (``sensor/NAME.yaml``, ``generator/NAME.yaml``, ...) then join tnf's config groups, so
``tnf touch sensor=NAME`` selects them.
"""

from __future__ import annotations

import importlib.metadata as md

from hydra.core.config_search_path import ConfigSearchPath
from hydra.plugins.search_path_plugin import SearchPathPlugin


class TnfSearchPathPlugin(SearchPathPlugin):
    def manipulate_search_path(self, search_path: ConfigSearchPath) -> None:
        # Only for tnf's own apps: other Hydra programs in the same environment are left alone.
        if not any(e.provider == "main" and _is_tnf(e.path) for e in search_path.get_path()):
            return
        for ep in sorted(md.entry_points(group="tnf.conf"), key=lambda e: e.name):
            provider = ep.dist.name if ep.dist is not None else ep.name
            search_path.append(provider=provider, path=f"pkg://{_package(ep, provider)}")


def _package(ep: md.EntryPoint, provider: str) -> str:
    """The package that a ``tnf.conf`` entry point names; a TnfError when it is not installed (Hydra would skip it,
    and its options would be unknown)."""
    import importlib.util

    from tnf.errors import TnfError

    package = ep.value.split(":")[0].strip()
    try:
        found = importlib.util.find_spec(package) is not None
    except ImportError:  # a parent package is missing
        found = False
    if not found:
        raise TnfError(
            f"tnf.conf entry point {ep.name!r} of {provider} names {package!r}, which is not installed; "
            f"fix the entry point in {provider}'s pyproject.toml and reinstall it"
        )
    return package


def _is_tnf(path: str | None) -> bool:
    import os

    from tnf.env import conf_dir

    if not path:
        return False
    p = path.removeprefix("file://")
    return os.path.abspath(p) == os.path.abspath(conf_dir())
