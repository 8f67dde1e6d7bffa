"""Infrastructure of the service, apart from the routes: settings, database, tokens, errors, events, files."""
