"""The job service's workers: one Celery app, one thin task per pipeline stage, the runner
that holds a stage's lease while it runs, and the reconciler that re-queues lost work."""
