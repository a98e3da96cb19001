"""The HTTP adapter: FastAPI routes, the request schemas, middleware, errors and the web page."""
