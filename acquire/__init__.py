"""Acquisition: turn an orbit into motion, exposures and a scan file (plan, pre-flight, engine, recorder)."""
