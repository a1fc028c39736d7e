"""One module per ``cubeloc`` verb; see ``daemon.cli``."""
