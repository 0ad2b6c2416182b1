"""The web viewer of a converted scene (``phirie view OUT_DIR``; viser, the ``viewer`` extra)."""
