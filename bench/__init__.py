"""Benchmarks (``make bench``): each module measures one thing and rewrites its own section
of ``docs/benchmarks.md``. Speed is measured here, never by timed asserts in tests.

A module has ``TITLE`` and ``run() -> str`` (a Markdown block: a table plus a line on how
it was measured). ``python -m bench [NAME ...]`` runs all modules or the named ones.
"""
