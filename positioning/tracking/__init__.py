"""Initialisation on the target, then a metric monocular tracker the target keeps honest.

``TrackingProcessor`` (processor.py) is the ``FrameProcessor`` the daemon and ``cubeloc
track`` run. Inside: ``features`` (Shi-Tomasi corners tracked with KLT), ``initialiser``
(the paper's Algorithms 1 and 2), ``tracker`` (PnP on the map, keyframes, triangulation,
target anchoring, lost/relocalised states), ``bundle`` (sliding-window bundle adjustment
with SciPy), ``map`` (keyframes and points), ``relocalise`` (ORB against keyframes),
``twoview`` (normalised-coordinate geometry) and ``options`` (every tunable).
"""

from cubeloc.positioning.tracking.initialiser import InitStatus
from cubeloc.positioning.tracking.options import TrackerOptions
from cubeloc.positioning.tracking.processor import ProcessorOptions, TrackingProcessor

__all__ = ["InitStatus", "ProcessorOptions", "TrackerOptions", "TrackingProcessor"]
