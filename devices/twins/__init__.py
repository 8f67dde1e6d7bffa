"""Simulated twins: real servers on real sockets speaking each device's protocol, with simple physics."""
