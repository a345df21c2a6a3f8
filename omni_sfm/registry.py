"""Plugins found through entry points, so third parties add one without editing the core.

Groups (the contract of each: docs/plugins.md):

- ``omni_sfm.initializers``: pose initializers compared by ``omni-sfm compare``: a callable
  ``(sequence: SequenceInput, options: Mapping[str, Any]) -> InitializerResult``
  (:mod:`omni_sfm.plugin_contract`).
- ``omni_sfm.adapters``: adapters for users' own pycolmap / Open3D scripts (callables).

A distribution registers one in its ``pyproject.toml``::

    [project.entry-points."omni_sfm.adapters"]
    my-adapter = "my_package.module:function"

The core never imports a plugin by name: it asks this registry, which checks what an entry
point loads (a plugin that cannot be imported or is not a callable raises
:class:`PluginError`; :func:`omni_sfm.plugin_contract.check_result` checks what an initializer
returns).
"""

from __future__ import annotations

from importlib.metadata import EntryPoint, entry_points
from typing import Any

from omni_sfm.errors import OmniSfmError

INITIALIZERS = "omni_sfm.initializers"
ADAPTERS = "omni_sfm.adapters"

GROUPS = (INITIALIZERS, ADAPTERS)
"""The entry-point groups of omni-sfm; what each loads must be callable."""


class PluginError(OmniSfmError):
    """A registered plugin is broken: it cannot be imported or is not what its group needs."""


def available(group: str) -> dict[str, EntryPoint]:
    """The entry points registered in ``group``, by name."""
    return {ep.name: ep for ep in entry_points(group=group)}


def load(group: str, name: str) -> Any:
    """The object registered as ``name`` in ``group``, checked.

    Raises:
        OmniSfmError: no plugin ``name`` in ``group`` (the message names the known ones).
        PluginError: the plugin cannot be imported, or (for a group of :data:`GROUPS`) what it
            loads is not callable; one line naming the plugin and its entry point.
    """
    eps = available(group)
    if name not in eps:
        known = ", ".join(sorted(eps)) or "none installed"
        raise OmniSfmError(f"unknown {group.rsplit('.', 1)[-1][:-1]} {name!r} (known: {known})")
    ep = eps[name]
    try:
        obj = ep.load()
    except Exception as exc:  # a broken plugin, whatever its error, is reported in one line
        first = str(exc).splitlines()[0] if str(exc) else ""
        raise PluginError(f"plugin {name!r} of {group} ({ep.value}) cannot be loaded: "
                          f"{type(exc).__name__}: {first}") from None
    if group in GROUPS and not callable(obj):
        raise PluginError(f"plugin {name!r} of {group} ({ep.value}) loads an object of type "
                          f"{type(obj).__qualname__}, not a callable (docs/plugins.md)")
    return obj
