"""Device drivers behind one API (``devices.base``), each with a simulated twin (``devices.twins``)."""
