"""Plugins shipped with omni-sfm, registered through entry points (see omni_sfm.registry)."""
