"""The web console: server-rendered pages for lab technicians, made live by the REST API and its event streams."""
