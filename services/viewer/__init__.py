"""Web viewer: a WebGL2 page (built from ``services/viewer/src`` with npm into ``dist``) that flies
through a job's Potree 2.0 tiles, and the FastAPI routes serving it (:mod:`services.viewer.routes`)."""
