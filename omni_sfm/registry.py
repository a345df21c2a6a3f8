"""Plugins found through entry points, so third parties add one without editing the core.

Groups:

- ``omni_sfm.initializers``: pose initializers compared by ``omni-sfm compare`` (a callable
  ``(images, camera, options) -> Trajectory``-like result; see docs/plugins.md).
- ``omni_sfm.adapters``: adapters for users' own pycolmap / Open3D scripts.

A distribution registers one in its ``pyproject.toml``::

    [project.entry-points."omni_sfm.adapters"]
    my-adapter = "my_package.module:function"

The core never imports a plugin by name: it asks this registry.
"""

from __future__ import annotations

from importlib.metadata import EntryPoint, entry_points
from typing import Any

from omni_sfm.errors import OmniSfmError

INITIALIZERS = "omni_sfm.initializers"
ADAPTERS = "omni_sfm.adapters"


def available(group: str) -> dict[str, EntryPoint]:
    """The entry points registered in ``group``, by name."""
    return {ep.name: ep for ep in entry_points(group=group)}


def load(group: str, name: str) -> Any:
    """The object registered as ``name`` in ``group``; OmniSfmError names the known ones."""
    eps = available(group)
    if name not in eps:
        known = ", ".join(sorted(eps)) or "none installed"
        raise OmniSfmError(f"unknown {group.rsplit('.', 1)[-1][:-1]} {name!r} (known: {known})")
    try:
        return eps[name].load()
    except ImportError as exc:
        raise OmniSfmError(f"plugin {name!r} of {group} cannot be imported: {exc}") from None
