"""Tactile simulation: the simulator interface (``base``), the warp gel simulator and touch sampling."""
