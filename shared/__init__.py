"""Graylight's scanning science and data contracts.

Plain, typed, vectorised functions and dataclasses: no queue, no HTTP. The job
service (``workers/``) and the API and render services (``services/``) import
these; the embedded ``graylight scan`` calls them in-process.
"""

__version__ = "0.1.0"
