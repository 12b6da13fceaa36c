"""The job contract: declared transitions, the graph, content addresses, what a retry re-runs."""

from __future__ import annotations

import pytest

from shared.service.jobs import (
    GRAPHS,
    JOB_TRANSITIONS,
    STAGE_TRANSITIONS,
    IllegalTransition,
    JobState,
    StageState,
    StageView,
    check_transition,
    graph_for,
    row_key,
    rows_to_rerun,
    stage_key,
    stage_sources,
    stage_spec,
)


def test_transitions_cover_every_state() -> None:
    assert set(JOB_TRANSITIONS) == set(JobState)
    assert set(STAGE_TRANSITIONS) == set(StageState)
    assert stage_sources(StageState.FAILED) == {StageState.QUEUED, StageState.RUNNING}
    assert stage_sources(StageState.RUNNING) == {StageState.QUEUED}


def test_check_transition_refuses_undeclared_moves() -> None:
    check_transition(None, JobState.QUEUED, JobState.RUNNING)
    check_transition("decode", StageState.RUNNING, StageState.SUCCEEDED)
    check_transition("decode", None, StageState.PENDING)  # creation
    with pytest.raises(IllegalTransition, match="stage decode: succeeded -> running"):
        check_transition("decode", StageState.SUCCEEDED, StageState.RUNNING)
    with pytest.raises(IllegalTransition, match="job: succeeded -> running"):
        check_transition(None, JobState.SUCCEEDED, JobState.RUNNING)


def test_render_switch_drops_downstream_stages() -> None:
    full = [s.name for s in graph_for("scan")]
    off = [s.name for s in graph_for("scan", {"render": False})]
    assert "preview" in full and "tiles" in full
    assert off == [n for n in full if not n.startswith(("tiles", "preview"))]


def test_row_key_includes_the_fanout_index() -> None:
    spec = stage_spec("scan", "tiles_chunk")
    a = row_key("scan", "tiles_chunk#0", "cap", {}, {"tiles_plan": "k"})
    b = row_key("scan", "tiles_chunk#1", "cap", {}, {"tiles_plan": "k"})
    assert a != b
    assert a == stage_key(spec, "cap", {}, {"tiles_plan": "k"}, 0)


def _rows(keys: dict[str, str], states: dict[str, str] | None = None) -> list[StageView]:
    states = states or {}
    return [StageView(s.name, states.get(s.name, StageState.SUCCEEDED), s.depends_on, keys.get(s.name))
            for s in graph_for("scan", {"render": False})]  # fmt: skip


def _keys(params: dict) -> dict[str, str]:
    keys: dict[str, str] = {}
    for s in graph_for("scan", {"render": False}):
        keys[s.name] = row_key("scan", s.name, "cap", params, {d: keys[d] for d in s.depends_on})
    return keys


def _downstream(name: str) -> set[str]:
    out: set[str] = set()
    for s in graph_for("scan", {"render": False}):
        if name in s.depends_on or out & set(s.depends_on):
            out.add(s.name)
    return out


def test_rows_to_rerun() -> None:
    keys = _keys({"render": False})
    assert rows_to_rerun("scan", _rows(keys), "cap", {"render": False}) == set()
    # A failed stage re-runs with everything downstream of it, nothing upstream.
    failed = rows_to_rerun("scan", _rows(keys, {"decode": StageState.FAILED}), "cap", {"render": False})
    assert failed == {"decode"} | _downstream("decode")
    assert "ingest" not in failed and {"triangulate", "compress", "export"} <= failed
    # A parameter that ingest and triangulate read (the rig) re-runs them and what follows.
    rig = rows_to_rerun("scan", _rows(keys), "cap", {"render": False, "rig": "other"})
    assert rig == {"ingest"} | _downstream("ingest")


def test_graphs_declare_known_queues() -> None:
    from shared.service.jobs import QUEUES

    for specs in GRAPHS.values():
        for s in specs:
            assert s.queue in QUEUES and s.queue != "control"
