"""Graylight's edges: the command line, the HTTP API, the render service and the web viewer."""
