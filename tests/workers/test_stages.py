"""The two registries agree: every stage of every job graph has an adapter, and every adapter
belongs to a stage of some graph; each stage has a Celery task of a stable name."""

from __future__ import annotations

from pathlib import Path

from shared.service.config import get_settings
from shared.service.jobs import GRAPHS, all_stage_specs
from shared.service.queue import task_name
from workers.celery_app import make_app
from workers.stages import STAGE_FUNCS


def test_every_graph_stage_has_an_adapter_and_back() -> None:
    in_graphs = {spec.name for specs in GRAPHS.values() for spec in specs}
    assert in_graphs - set(STAGE_FUNCS) == set(), "stages without an adapter in workers/stages.py"
    assert set(STAGE_FUNCS) - in_graphs == set(), "adapters of no stage in shared/service/jobs.py GRAPHS"


def test_graph_inputs_name_earlier_stages() -> None:
    for kind, specs in GRAPHS.items():
        seen: set[str] = set()
        for spec in specs:
            assert set(spec.depends_on) <= seen, f"{kind}.{spec.name} reads a stage declared after it"
            if spec.fanout_from is not None:
                assert spec.fanout_from in seen, f"{kind}.{spec.name} fans out from an unknown stage"
            seen.add(spec.name)


def test_celery_task_names_are_stable(tmp_path: Path) -> None:
    app = make_app(get_settings({"GRAYLIGHT_DATA_DIR": str(tmp_path)}))
    for name in all_stage_specs():
        assert task_name(name) == f"graylight.stage.{name}"  # queued messages survive an upgrade
        assert task_name(name) in app.tasks
    assert task_name("tiles_chunk#7") == "graylight.stage.tiles_chunk"
    assert {"graylight.reconcile", "graylight.rerender_previews"} <= set(app.tasks)


def test_apps_of_different_settings_keep_their_own_tasks(tmp_path: Path) -> None:
    """A task registered as "shared" would reach every app finalized later in the process,
    where it would run with the first app's settings (its database, its store)."""
    import warnings

    from celery.exceptions import DuplicateTaskNameWarning

    with warnings.catch_warnings():
        warnings.simplefilter("error", DuplicateTaskNameWarning)
        apps = [make_app(get_settings({"GRAYLIGHT_DATA_DIR": str(tmp_path / n)})) for n in "ab"]
        tasks = [a.tasks[task_name("decode")] for a in apps]  # finalizes both apps
    assert tasks[0] is not tasks[1]
    assert [t.app for t in tasks] == apps


def test_each_task_is_routed_to_its_queue_without_deprecated_attributes(tmp_path: Path) -> None:
    """Every task reaches its queue through the configuration's routes (the worker app's and the
    API's publisher alike), and registering them warns of nothing: Celery 5.7 deprecates a
    task's own ``queue`` attribute, which the app set on every task (66 warnings a suite)."""
    import warnings

    from shared.service.queue import RECONCILE_TASK, RERENDER_PREVIEW_TASK, RERENDER_TASK, publisher

    settings = get_settings({"GRAYLIGHT_DATA_DIR": str(tmp_path), "GRAYLIGHT_QUEUE_PREFIX": "rt-"})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        app = make_app(settings)
        app.tasks[task_name("decode")]  # finalizes the app: every task registered
    want = {task_name(n): settings.queue(s.queue) for n, s in all_stage_specs().items()}
    want |= {RECONCILE_TASK: settings.queue("control"), RERENDER_TASK: settings.queue("control"),
             RERENDER_PREVIEW_TASK: settings.queue("render")}  # fmt: skip
    assert len(set(want.values())) >= 3  # the stages' queues differ: a wrong route would show
    for sender in (app, publisher(settings)):
        for name, queue in want.items():
            assert sender.amqp.router.route({}, name)["queue"].name == queue, name
