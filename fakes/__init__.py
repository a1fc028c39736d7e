"""The synthetic camera: the target in a textured room, rendered with exact ground truth.

``render_view`` draws one frame; ``make_trajectory`` makes camera paths with ground truth;
``SyntheticCamera`` streams them through the camera protocol (source
``synthetic:TRAJECTORY``); ``write_synthetic_sequence`` writes them as EuRoC sequences.
"""

from cubeloc.fakes.camera import RenderOptions, SyntheticCamera, open_synthetic_source
from cubeloc.fakes.render import render_view
from cubeloc.fakes.room import Box, Room, default_room
from cubeloc.fakes.sequence import write_synthetic_sequence
from cubeloc.fakes.trajectories import TRAJECTORIES, make_trajectory

__all__ = [
    "TRAJECTORIES",
    "Box",
    "RenderOptions",
    "Room",
    "SyntheticCamera",
    "default_room",
    "make_trajectory",
    "open_synthetic_source",
    "render_view",
    "write_synthetic_sequence",
]
