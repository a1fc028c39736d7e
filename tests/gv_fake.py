"""Tests import the GigE Vision fake from here; it lives in ``drivers.fake_gige`` so that the
benchmarks use the same one."""

from cubeloc.drivers.fake_gige import FAKE_GV_CAMERA, GVCP_PORT, GvFake, gvcp_listening

__all__ = ["FAKE_GV_CAMERA", "GVCP_PORT", "GvFake", "gvcp_listening"]
