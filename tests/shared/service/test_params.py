"""Job parameters are checked at the edge, naming the field."""

from __future__ import annotations

import pytest

from shared.core.errors import InputError
from shared.service.params import check_job_params
from tests.support.hostile import bare_failures


def test_good_params_pass_through() -> None:
    params = {"render": True, "tiles": {"max_leaf": 5000}, "preview": {"size": [640, 480], "seconds": 2, "path": "dolly"}}
    assert check_job_params("scan", params) == params
    assert check_job_params("probe", {"seconds": 0.5}) == {"seconds": 0.5}
    assert check_job_params("scan", {}) == {}
    inline = {"preview": {"camera": {"fov": 40, "keyframes": [{"eye": [0, 0, 0], "target": [0, 0, 0]},
                                                               {"eye": [10, 0, 0], "target": [0, 0, 500]}]}}}
    assert check_job_params("multiview", inline) == inline  # a target on the eye looks at the scene's centre


@pytest.mark.parametrize(
    ("kind", "params", "field", "problem"),
    [
        ("scan", {"preview": {"size": [641, 480]}}, "params.preview.size", "even"),
        ("scan", {"preview": {"size": "big"}}, "params.preview.size", "[width, height]"),
        ("scan", {"preview": {"seconds": 0}}, "params.preview.seconds", "(0, 600]"),
        ("scan", {"preview": {"fps": 1000}}, "params.preview.fps", "[1, 120]"),
        ("scan", {"preview": {"colour": "red"}}, "params.preview", "unknown option"),
        ("scan", {"tiles": {"max_leaf": 10}}, "params.tiles.max_leaf", "in 100..1000000"),
        # Finding 9: every number bounded at intake (max_chunk of 1e30 failed after the job had run).
        ("scan", {"tiles": {"max_chunk": 10**30}}, "params.tiles.max_chunk", "in 100..50000000"),
        ("scan", {"compress": {"quantum": 1e300}}, "params.compress.quantum", "up to 1000"),
        # Finding 2: a job names no file on the worker; keyframes come inline and are checked.
        ("scan", {"preview": {"path": "/dev/zero"}}, "params.preview.path", "one of auto, arc, orbit, dolly"),
        ("scan", {"preview": {"path": "cam.json"}}, "params.preview.path", "inline in params.preview.camera"),
        ("scan", {"preview": {"camera": {"keyframes": []}}}, "params.preview.camera", "non-empty 'keyframes'"),
        ("scan", {"preview": {"camera": {"keyframes": [{"eye": [0, 0, 1e300], "target": [0, 0, 0]}]}}},
         "params.preview.camera.keyframes[0].eye", "magnitude at most"),
        ("scan", {"preview": {"camera": {"keyframes": [{"eye": [0, 0, 1], "target": [0, 0, 0], "t": 0}]}}},
         "params.preview.camera.keyframes[0].t", "unknown field"),
        ("scan", {"preview": {"camera": {"fov": 0, "keyframes": [{"eye": [0, 0, 1], "target": [0, 0, 0]}]}}},
         "params.preview.camera.fov", "[1, 170]"),
        ("scan", {"preview": {"camera": {"keyframes": [{"eye": [0, 0, 1], "target": [0, 0, 0]}] * 65}}},
         "params.preview.camera.keyframes", "at most 64"),
        ("scan", {"render": "yes"}, "params.render", "true or false"),
        ("scan", {"preveiw": {}}, "params.preveiw", "unknown parameter"),
        ("scan", {"rig": "x"}, "params.rig", "multipart field 'rig'"),
        ("scan", {"preview_epoch": 3}, "params.preview_epoch", "set by the service"),
        ("probe", {"seconds": 61}, "params.seconds", "0..60"),
        # an integer past float's range, or an infinite size: bare OverflowErrors from isfinite and int()
        ("probe", {"seconds": 10**400}, "params.seconds", "0..60"),
        ("scan", {"preview": {"seconds": 10**400}}, "params.preview.seconds", "(0, 600]"),
        ("scan", {"preview": {"size": [float("inf"), 480]}}, "params.preview.size", "[width, height]"),
        ("scan", {"compress": {"max_error": 10**400}}, "params.compress.max_error", "up to 1000"),
        ("scan", {"preview": {"camera": {"keyframes": [{"eye": [0, 0, 10**400], "target": [0, 0, 0]}]}}},
         "params.preview.camera.keyframes[0].eye", "3 finite numbers"),
        ("calibrate", {"render": False}, "params.render", "accepted: none"),
        ("scan", [], "params", "JSON object"),
    ],
)
def test_bad_params_name_the_field(kind: str, params: object, field: str, problem: str) -> None:
    with pytest.raises(InputError) as err:
        check_job_params(kind, params)
    assert str(err.value).startswith(f"{field}: ") and problem in str(err.value), str(err.value)


def test_service_params_from_the_store_are_allowed() -> None:
    assert check_job_params("scan", {"rig": "object:abc", "preview_epoch": 2}, allow_service=True)["rig"] == "object:abc"


def test_every_kind_and_parameter_has_a_schema() -> None:
    from shared.service.jobs import GRAPHS
    from shared.service.params import PARAMS, params_schema

    assert set(PARAMS) == set(GRAPHS)
    for kind, accepted in PARAMS.items():
        schema = params_schema(kind)
        assert schema["additionalProperties"] is False and set(schema["properties"]) == set(accepted)
        assert all(p.schema.get("type") or p.schema.get("anyOf") for p in accepted.values()), kind


def test_derivatives_parameter_names_levels_and_fields() -> None:
    from shared.service.params import check_job_params

    ok = {"derivatives": {"levels": ["thumb", {"name": "low", "faces": 50000, "texture_px": 512}], "colour": "shaded"}}
    assert check_job_params("multiview", ok) == ok
    assert check_job_params("multiview", {"derivatives": False}) == {"derivatives": False}
    for bad, field in (({"levels": ["huge"]}, "params.derivatives.levels"),
                       ({"levels": [{"name": "low", "faces": 0}]}, "params.derivatives.levels.low.faces"),
                       ({"levels": [{"name": "low", "texture_px": 100000}]}, "params.derivatives.levels.low.texture_px"),
                       ({"colour": "glossy"}, "params.derivatives.colour"), ({"lod": 1}, "params.derivatives.lod"),
                       (3, "params.derivatives")):
        with pytest.raises(InputError, match=field.replace(".", r"\.") + ":"):
            check_job_params("multiview", {"derivatives": bad})


@pytest.mark.parametrize("kind", ["scan", "multiview", "probe"])
def test_every_field_of_full_params_refused_by_name_not_a_bare_exception(kind: str) -> None:
    """Every field of a full set of parameters replaced by what a careless or hostile client
    sends (tests.support.hostile): each is accepted or refused with an InputError naming it."""
    full = {"render": True, "export": True, "drop_unregistered": False,
            "derivatives": {"levels": ["thumb", {"name": "low", "faces": 1000, "texture_px": 256, "jpeg_quality": 80}],
                            "colour": "photo"},
            "tiles": {"max_chunk": 100_000, "max_leaf": 10_000, "node_codec": "octree"},
            "preview": {"size": [640, 360], "seconds": 4, "fps": 30,
                        "camera": {"fov": 40, "keyframes": [{"eye": [0, 0, 1], "target": [0, 0, 0]}]}},
            "compress": {"quantum": 0.02, "keep_range": True}, "title": "A", "collection": "B", "identifier": "C"}
    params = {"probe": {"seconds": 1}, "scan": {k: v for k, v in full.items() if k not in ("derivatives", "drop_unregistered")},
              "multiview": full}[kind]
    check_job_params(kind, params)  # as written, accepted
    assert not bare_failures(params, lambda d: check_job_params(kind, d), InputError)
