"""The report of a batch: one row per capture, for a registrar to file.

In: the jobs of one batch (:class:`~shared.service.jobstore.Job` records with their stages)
and the files it refused at intake (:class:`~shared.service.jobstore.Reject`).
Out: :class:`CaptureRow` records — the capture's name as submitted, its job's state (or
``rejected``), the number of points its cloud holds, the failure reason in one line, and the
names of the artifacts it published (``cloud.ply``, ``preview.mp4``, ...) — and their CSV and
JSON forms. Every file sent has its row: a refused file is never left out of the report.

Reads nothing but the job records: the points come from the triangulation (or merge) stage's
summary and the artifact names from the stages' summaries (``published``: the files each wrote)
and the job graph's ``publish`` lists of the stages that succeeded,
so a report of a thousand captures costs one query.
"""

from __future__ import annotations

import csv
import io
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from typing import Any

from shared.service.jobs import JOB_TERMINAL, JobState, StageState, stage_spec
from shared.service.jobstore import REJECTED, Job, Reject

__all__ = ["CSV_COLUMNS", "QA_REPORT", "SCENE_PATH", "CaptureRow", "capture_row", "report_csv", "report_rows", "scene_url", "summarize"]

#: Columns of the CSV report, in order (``artifacts`` is space-separated).
CSV_COLUMNS = ("capture", "job", "state", "points", "error", "artifacts", "verdict", "scene", "qa_report")
#: The route that hands out a published object's Voyager link (``/v1/jobs/{job}/scene``) and the QA report's name.
SCENE_PATH = "/v1/jobs/{job}/scene"
QA_REPORT = "qa.html"


@dataclass(frozen=True)
class CaptureRow:
    """One capture of a batch: ``capture`` is its name as submitted, ``points`` the size of
    its cloud (None before triangulation; a multi-view job's merged cloud), ``job`` None for a
    file refused at intake (``state`` rejected), ``error`` the one-line failure reason (None unless
    failed or cancelled), ``artifacts`` the short names it published, in graph order."""

    capture: str
    job: str | None
    state: str
    points: int | None
    error: str | None
    artifacts: list[str] = field(default_factory=list)
    #: The publish stage's verdict line (``publishable`` or why not; shared.publish.qa), None before it ran.
    verdict: str | None = None

    @property
    def published(self) -> bool:
        """Whether the publish stage left its scene and QA report (the report then links them)."""
        return self.job is not None and "scene.svx.json" in self.artifacts and QA_REPORT in self.artifacts


def _one_line(text: str | None) -> str | None:
    return " ".join(text.split()) if text else None


def capture_row(job: Job) -> CaptureRow:
    """The report row of one job."""
    points: int | None = None
    verdict: str | None = None
    published: list[str] = []
    for st in job.stages:
        if st.state != StageState.SUCCEEDED:
            continue
        summary = st.summary or {}
        if st.name in ("triangulate", "mv_merge") and isinstance(summary.get("points"), int):
            points = int(summary["points"])
        if st.name == "publish" and isinstance(summary.get("verdict"), str):
            verdict = _one_line(summary["verdict"])
        for name in stage_spec(job.kind, st.name).published_names(summary):
            if name not in published:
                published.append(name)
    error = _one_line(job.error)
    if error is None and job.state == JobState.CANCELLED:
        error = "cancelled"
    return CaptureRow(capture=job.name, job=job.id, state=job.state, points=points, error=error, artifacts=published,
                      verdict=verdict)


def report_rows(jobs: Iterable[Job], rejects: Iterable[Reject] = ()) -> list[CaptureRow]:
    """Rows of a batch's jobs and refused files, in submission order (oldest first; the files a
    request refused after the jobs it made)."""
    keyed = [((j.created_at, 0, j.id), capture_row(j)) for j in jobs]
    keyed += [((r.at, 1, str(i)), CaptureRow(capture=r.capture, job=None, state=REJECTED, points=None, error=r.error))
              for i, r in enumerate(rejects)]  # fmt: skip
    return [row for _k, row in sorted(keyed, key=lambda kr: kr[0])]


def summarize(rows: Iterable[CaptureRow]) -> dict[str, Any]:
    """Counts by state, the total, and the finished fraction (1.0 for an empty batch)."""
    counts: dict[str, int] = {}
    for r in rows:
        counts[r.state] = counts.get(r.state, 0) + 1
    total = sum(counts.values())
    done = sum(n for s, n in counts.items() if s in JOB_TERMINAL or s == REJECTED)
    return {"total": total, "counts": counts, "progress": done / total if total else 1.0}


def report_csv(rows: Iterable[CaptureRow], link: Callable[[CaptureRow, str], str] | None = None,
               base: str = "") -> str:
    """The CSV text of ``rows`` (header :data:`CSV_COLUMNS`); ``link(row, name)`` turns an
    artifact name into its URL (default: the bare name); ``base`` goes before the scene route's path.
    A published object's ``scene`` is the route that gives its Voyager link, ``qa_report`` its qa.html."""
    out = io.StringIO()
    w = csv.writer(out, lineterminator="\n")
    w.writerow(CSV_COLUMNS)
    for r in rows:
        links = [link(r, a) if link else a for a in r.artifacts]
        w.writerow([r.capture, r.job or "", r.state, "" if r.points is None else r.points, r.error or "", " ".join(links),
                    r.verdict or "", scene_url(r, base) or "",
                    (link(r, QA_REPORT) if link else QA_REPORT) if r.published else ""])
    return out.getvalue()


def scene_url(row: CaptureRow, base: str = "") -> str | None:
    """Where the owner of a published object gets its Voyager link (``base`` + :data:`SCENE_PATH`), else None."""
    return f"{base}{SCENE_PATH.format(job=row.job)}" if row.published else None


def row_json(row: CaptureRow) -> dict[str, Any]:
    return asdict(row)
