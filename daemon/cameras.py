"""The camera sources the daemon offers: drivers' own (aravis, replay) and the synthetic
camera of fakes/, registered here so that drivers/ knows nothing of fakes/.

Everything in daemon/ (and the tests) makes cameras through this module.
"""

from __future__ import annotations

from cubeloc.drivers.registry import make_camera, parse_source, register_backend

register_backend("synthetic", "cubeloc.fakes.camera:open_synthetic_source")

__all__ = ["make_camera", "parse_source"]
