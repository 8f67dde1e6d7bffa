"""The REST service: ``create_app(settings)`` and ``orbitct serve``; see ``app.py``."""
