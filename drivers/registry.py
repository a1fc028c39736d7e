"""Choose a camera backend by name, importing it only when used.

A camera source is a string ``BACKEND[:ARGUMENT]``:

========================  ======================================================
``aravis``                the first GigE Vision / USB3 Vision camera Aravis finds
``aravis:ID``             an Aravis device id, serial number or IP address
``replay:DIR``            a recorded sequence in the EuRoC layout (as fast as possible)
``replay:DIR@pace``       the same, at the recorded pace
========================  ======================================================

Other backends are registered by the layer that owns them: ``daemon/cameras.py`` adds
``synthetic:TRAJECTORY`` (the synthetic camera of ``fakes``), so drivers/ never reaches
up into fakes/. The pipeline imports this module, never ``gi``: the Aravis backend (and
so PyGObject) is imported only when an ``aravis`` source is opened.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable

from cubeloc.drivers.base import Camera, CameraNotFound, CameraSettings

# backend name -> "module:factory"; a factory takes (argument, settings) -> Camera
BACKENDS: dict[str, str] = {
    "aravis": "cubeloc.drivers.aravis_camera:open_aravis_source",
    "replay": "cubeloc.drivers.replay:open_replay_source",
}


def register_backend(name: str, factory: str) -> None:
    """Offer ``name:ARGUMENT`` sources, built by ``factory`` ("module:function", imported
    when such a source is first made)."""
    if ":" in name or not name:
        raise ValueError(f"a backend name is one word, got {name!r}")
    BACKENDS[name] = factory


def parse_source(source: str) -> tuple[str, str]:
    """Split ``BACKEND[:ARGUMENT]``; raise CameraNotFound naming the known backends."""
    backend, _, argument = source.partition(":")
    if backend not in BACKENDS:
        known = ", ".join(sorted(BACKENDS))
        raise CameraNotFound(
            f"unknown camera source {source!r}: expected BACKEND[:ARGUMENT] with BACKEND one of {known}"
        )
    return backend, argument


def make_camera(source: str, settings: CameraSettings | None = None) -> Camera:
    """Build (not open) the camera for ``source``."""
    backend, argument = parse_source(source)
    module_name, _, factory_name = BACKENDS[backend].partition(":")
    module = importlib.import_module(module_name)
    factory: Callable[[str, CameraSettings], Camera] = getattr(module, factory_name)
    return factory(argument, settings or CameraSettings())
