"""The rig process (devices and the scan loop, away from the web server) and the web side's handle on it."""

#: every reason a scan is aborted for because the service itself is going away begins so (a restart tells these
#: scans, interrupted, from those that had ended on their own before it)
SERVICE_STOPPED = "the service stopped"
