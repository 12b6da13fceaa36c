"""The job service's own records: configuration, job states and graphs, job parameters, the
job store, the artifact store, archive intake, admission against each key's limits, the
worker's capture cache and the broker contract (the queue publisher).

The science packages never import this one."""

from shared.core.lazy import lazy_exports

__all__, __getattr__, __dir__ = lazy_exports(
    __name__,
    {
        "Settings": "config",
        "get_settings": "config",
        "JobState": "jobs",
        "StageState": "jobs",
        "StageSpec": "jobs",
        "GRAPHS": "jobs",
        "QUEUES": "jobs",
        "graph_for": "jobs",
        "stage_spec": "jobs",
        "stage_key": "jobs",
        "row_key": "jobs",
        "rows_to_rerun": "jobs",
        "JobStore": "jobstore",
        "Job": "jobstore",
        "Stage": "jobstore",
        "Batch": "jobstore",
        "ApiKey": "jobstore",
        "NewJob": "jobstore",
        "check_job_params": "params",
        "ArtifactStore": "artifacts",
        "ArtifactError": "artifacts",
        "ArchiveLimits": "archive",
        "inspect_archive": "archive",
        "extract_archive": "archive",
        "pack_folder": "archive",
        "Admission": "admission",
        "LimitReached": "usage",
        "release_capture": "capture_cache",
        "publish_stages": "queue",
        "task_name": "queue",
        "celery_config": "queue",
    },
)
