"""Tactile simulation: the warp gel simulator and touch sampling."""
