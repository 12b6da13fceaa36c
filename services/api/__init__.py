"""The HTTP API of the job service (FastAPI): jobs, batches, uploads and artifacts."""
