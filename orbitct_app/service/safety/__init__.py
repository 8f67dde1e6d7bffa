"""The emergency stop: a latch every process honours, and a guard process with its own stop listener."""
