"""One APIRouter per resource of the job-service API; ``services.api.app.create_app`` includes them."""

from services.api.routers import artifacts, batches, health, jobs, metrics, scene, uploads

__all__ = ["ROUTERS", "artifacts", "batches", "health", "jobs", "metrics", "scene", "uploads"]

#: Every router, in the order the OpenAPI document lists them.
ROUTERS = (health.router, jobs.router, artifacts.router, batches.router, uploads.router, metrics.router,
           scene.router)
