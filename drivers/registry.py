"""Choose a camera backend by name, importing it only when used.

A camera source is a string ``BACKEND[:ARGUMENT]``:

========================  ======================================================
``aravis``                the first GigE Vision / USB3 Vision camera Aravis finds
``aravis:ID``             an Aravis device id, serial number or IP address
``replay:DIR``            a recorded sequence in the EuRoC layout (as fast as possible)
``replay:DIR@pace``       the same, at the recorded pace
``synthetic:TRAJECTORY``  the synthetic camera (``fakes``) along a named trajectory
========================  ======================================================

The pipeline imports this module, never ``gi``: the Aravis backend (and so PyGObject) is
imported only when an ``aravis`` source is opened.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable

from drivers.base import Camera, CameraNotFound, CameraSettings

# backend name -> "module:factory"; a factory takes (argument, settings) -> Camera
BACKENDS: dict[str, str] = {
    "aravis": "drivers.aravis_camera:open_aravis_source",
    "replay": "drivers.replay:open_replay_source",
    "synthetic": "fakes.camera:open_synthetic_source",
}


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
