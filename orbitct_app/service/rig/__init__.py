"""The rig process (devices and the scan loop, away from the web server) and the web side's handle on it."""
