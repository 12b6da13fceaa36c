"""Derivatives: budgets, the baked maps against a known colour, fallbacks, and every GLB through
the Khronos glTF-Validator."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest

from shared.core.errors import InputError
from shared.derive.bake import ColourSource, bake_maps, unwrap, vertex_normals
from shared.derive.levels import LEVELS, parse_levels
from shared.derive.pipeline import load_master, make_derivatives, simplify_to
from shared.formats.ply import read_ply
from tests.support.derive_scene import pattern, write_scene

VIEWER = Path(__file__).resolve().parents[3] / "services" / "viewer"
LEVELS_SPEC = "thumb:4000:256,low:20000:512"


@pytest.fixture(scope="module")
def scene(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_scene(tmp_path_factory.mktemp("derive") / "merge")


@pytest.fixture(scope="module")
def derived(scene: Path, tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("derived")
    return out, make_derivatives(scene, out, levels=LEVELS_SPEC, colour="albedo")


def test_levels_default_to_voyagers_and_nonsense_budgets_are_refused() -> None:
    names = [lv.name for lv in parse_levels(None)]
    assert names == ["thumb", "low", "medium", "high"]
    assert (LEVELS["thumb"].faces, LEVELS["thumb"].texture_px, LEVELS["thumb"].max_bytes) == (20_000, 512, 200_000)
    assert [LEVELS[n].texture_px for n in ("low", "medium", "high")] == [1024, 2048, 4096]
    assert parse_levels("low:100000:2048")[0].faces == 100_000
    assert parse_levels([{"name": "thumb", "texture_px": 256}])[0].faces == 20_000
    # A level named again replaces the earlier one in its place (what the job parameters allow).
    again = parse_levels(["low", "thumb", {"name": "low", "texture_px": 2048}])
    assert [(lv.name, lv.texture_px) for lv in again] == [("low", 2048), ("thumb", 512)]
    for spec, field in (("low:0:1024", "levels.low.faces"), ("low:150000:100000", "levels.low.texture_px"),
                        ("low:150000:1000", "levels.low.texture_px"), ("huge", "levels"),
                        ([{"name": "x", "faces": "many", "texture_px": 512}], "levels.x.faces: must be an integer"),
                        # a float was truncated (150000.5 faces read as 150000), an infinite one a bare
                        # OverflowError, a huge integer printed whole
                        ([{"name": "low", "faces": 150_000.5}], "levels.low.faces: must be an integer, got 150000.5"),
                        ([{"name": "low", "texture_px": float("inf")}], "levels.low.texture_px: must be an integer"),
                        ([{"name": "low", "faces": 10**400}], "levels.low.faces: must be in .*, got an integer of 401 digits")):
        with pytest.raises(InputError, match=field.replace(".", r"\.").replace(r"\.*", ".*")):
            parse_levels(spec)


def test_baked_colour_matches_the_known_surface_colour(scene: Path) -> None:
    v, f, _ = load_master(scene / "mesh.ply")
    pc = read_ply(scene / "merged.ply")
    lv, lf = simplify_to(v, f, 8000)
    m = unwrap(lv, lf, 1024)
    src = ColourSource(pc.xyz.astype(np.float64), pc.albedo, pc.normals, pc.size, "albedo")
    maps = bake_maps(m, 1024, src, v, vertex_normals(v, f))
    # Every covered texel's surface point, from the atlas, against the pattern there.
    from shared.derive._raster import rasterise_uv

    fid = np.full((1024, 1024), -1, np.int32)
    bary = np.zeros((1024, 1024, 3), np.float32)
    rasterise_uv(m.uv, m.faces, 1024, fid, bary)
    cov = fid >= 0
    P = np.einsum("nk,nkj->nj", bary[cov], m.vertices[m.faces[fid[cov]]])
    err = np.abs(maps.base_colour[cov].astype(int) - pattern(P).astype(int))
    print(f"baked colour: mean abs error {err.mean():.2f} levels, 99th pct {np.percentile(err, 99):.0f}")
    assert err.mean() < 4.0
    # Texels more than 40 levels from their 5x5 median (speckle): the baked map has none to speak of.
    med = cv2.medianBlur(maps.base_colour, 5)
    speckle = (np.abs(maps.base_colour.astype(int) - med.astype(int)).max(axis=2) > 40)[cov].mean()
    assert speckle < 0.01
    assert maps.covered.mean() > 0.3
    assert 0 <= maps.stats["bridged_share"] < 0.01
    # A level too coarse for the master's bumps carries them in its normal map: the map's normals
    # tilt from the level's own (128, 128, 255) as the master's normals tilt from the level's.
    cv_, cf = simplify_to(v, f, 300)
    coarse = unwrap(cv_, cf, 256)
    cmaps = bake_maps(coarse, 256, src, v, vertex_normals(v, f))
    fid = np.full((256, 256), -1, np.int32)
    rasterise_uv(coarse.uv, coarse.faces, 256, fid, np.zeros((256, 256, 3), np.float32))
    tilt = np.degrees(np.arccos(np.clip((cmaps.normal[fid >= 0][:, 2].astype(float) / 127.5 - 1), -1, 1)))
    fine_tilt = np.degrees(np.arccos(np.clip((maps.normal[cov][:, 2].astype(float) / 127.5 - 1), -1, 1)))
    print(f"normal map tilt, median: coarse level {np.median(tilt):.1f} deg, fine level {np.median(fine_tilt):.1f} deg")
    assert np.median(tilt) > 2 * np.median(fine_tilt)


def test_derivative_set_files_report_and_budgets(derived) -> None:
    out, report = derived
    names = sorted(p.name for p in out.iterdir())
    assert names == ["derivatives.json", "mesh_low.glb", "mesh_low_bridged.png", "mesh_thumb.glb",
                     "mesh_thumb_bridged.png"]
    assert json.loads((out / "derivatives.json").read_text()) == json.loads(json.dumps(report))
    assert report["colour_baked"] == "albedo" and not report["warnings"]
    for lv in report["levels"]:
        assert lv["faces"] <= lv["faces_budget"] * 1.01 and lv["faces"] >= 0.9 * min(lv["faces_budget"],
                                                                                      report["master"]["faces"])
        data = (out / lv["file"]).read_bytes()
        assert data[:4] == b"glTF" and len(data) == lv["bytes"]
        doc = json.loads(data[20:20 + int.from_bytes(data[12:16], "little")])
        assert doc["asset"]["extras"]["units"] == "mm" and doc["asset"]["extras"]["level"] == lv["level"]
        assert doc["extensionsRequired"] == ["KHR_draco_mesh_compression"]
        mask = cv2.imread(str(out / f"mesh_{lv['level']}_bridged.png"), cv2.IMREAD_UNCHANGED)
        assert mask.shape == (lv["texture_px"], lv["texture_px"])


def _validate(paths: list[Path]) -> list[dict]:
    node = shutil.which("node")
    if node is None or not (VIEWER / "node_modules" / "gltf-validator").is_dir():
        pytest.fail("node or services/viewer/node_modules/gltf-validator missing: run `make viewer`")
    script = (
        "const v = require('gltf-validator'); const fs = require('fs');"
        "(async () => { const out = [];"
        "for (const p of process.argv.slice(1)) {"
        "  const r = await v.validateBytes(new Uint8Array(fs.readFileSync(p)), {maxIssues: 50});"
        "  out.push({path: p, errors: r.issues.numErrors, warnings: r.issues.numWarnings,"
        "            messages: r.issues.messages.filter(m => m.severity === 0).map(m => m.code + ' ' + m.message)}); }"
        "console.log(JSON.stringify(out)); })();"
    )
    run = subprocess.run([node, "-e", script, *map(str, paths)], cwd=VIEWER, capture_output=True, text=True,
                         timeout=120, check=True)
    return json.loads(run.stdout)


def test_every_glb_passes_the_khronos_validator(derived, tmp_path: Path) -> None:
    out, report = derived
    results = _validate([out / lv["file"] for lv in report["levels"]])
    for r in results:
        print(r)
        assert r["errors"] == 0, r["messages"]
    # The validator does find errors: a GLB whose material names a texture that is not there.
    data = bytearray((out / report["levels"][0]["file"]).read_bytes())
    n = int.from_bytes(data[12:16], "little")
    doc = json.loads(data[20:20 + n])
    doc["materials"][0]["normalTexture"]["index"] = 99
    js = json.dumps(doc).encode()
    js += b" " * (-len(js) % 4)
    rest = bytes(data[20 + n:])
    broken = b"glTF" + (2).to_bytes(4, "little") + (12 + 8 + len(js) + len(rest)).to_bytes(4, "little")
    broken += len(js).to_bytes(4, "little") + b"JSON" + js + rest
    (tmp_path / "broken.glb").write_bytes(broken)
    assert _validate([tmp_path / "broken.glb"])[0]["errors"] > 0


def test_colour_fallbacks_and_bad_input(scene: Path, tmp_path: Path) -> None:
    # No albedo in the cloud: the shaded colour, with a warning.
    plain = write_scene(tmp_path / "plain", faces_subdiv=3, points=20_000, albedo=False)
    report = make_derivatives(plain, tmp_path / "o1", levels="t:500:128", colour="albedo")
    assert report["colour_baked"] == "shaded" and "no albedo" in report["warnings"][0]
    # The default bakes the views' photographs; a merge without them (no registration.json here)
    # bakes the cloud's colour and says why.
    report = make_derivatives(plain, tmp_path / "o1b", levels="t:500:128")
    assert report["colour"] == "photo" and report["colour_baked"] == "shaded"
    assert "no photographs to bake from (no registration.json" in report["warnings"][0]
    (plain / "registration.json").write_text('{"views": [{"name": "v0", "registered": true, "R": [[1, 0, 0]], '
                                             '"T": [0, 0, 0]}]}')
    (plain / "report.json").write_text('{"scanset": "%s"}' % (tmp_path / "gone"))
    report = make_derivatives(plain, tmp_path / "o1c", levels="t:500:128")
    assert "the scan set cannot be read" in report["warnings"][0]
    # No cloud at all: the master's vertex colours.
    (plain / "merged.ply").unlink()
    report = make_derivatives(plain, tmp_path / "o2", levels="t:500:128", colour="albedo")
    assert report["colour_baked"] == "mesh" and "vertex colours" in report["warnings"][0]
    with pytest.raises(InputError, match="colour"):
        make_derivatives(plain, tmp_path / "o3", colour="glossy")
    with pytest.raises(InputError, match="master mesh not found"):
        make_derivatives(tmp_path / "nothing", tmp_path / "o4")
    # A mesh too small to unwrap: one line naming it, nothing half-written.
    import trimesh

    tiny = tmp_path / "tiny"
    tiny.mkdir()
    trimesh.Trimesh([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], [[0, 1, 2], [0, 2, 3]]).export(tiny / "mesh.ply")
    with pytest.raises(InputError, match="too few to unwrap"):
        make_derivatives(tiny, tmp_path / "o5", levels="t:500:128")
    assert not list((tmp_path / "o5").iterdir())


def test_command_line(scene: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from services.cli.main import main

    assert main(["derivatives", str(scene), "--out", str(tmp_path / "cli"), "--levels", "thumb:2000:256"]) == 0
    out = capsys.readouterr().out
    assert "thumb" in out and "budget 200 kB: within" in out and (tmp_path / "cli" / "mesh_thumb.glb").is_file()
    assert main(["derivatives", str(scene), "--out", str(tmp_path / "bad"), "--levels", "thumb:0:256"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "levels.thumb.faces" in err[0]


def test_surface_bridged_without_data_is_marked(tmp_path: Path) -> None:
    from shared.formats.ply import write_ply

    folder = write_scene(tmp_path / "holed", faces_subdiv=4, points=60_000)
    pc = read_ply(folder / "merged.ply")
    keep = pc.xyz[:, 2] < 25.0  # no sample on the top cap: the master bridges it
    write_ply(folder / "merged.ply", pc.xyz[keep], rgb=pc.rgb[keep], normals=pc.normals[keep], size=pc.size[keep],
              albedo=pc.albedo[keep], albedo_weight=pc.albedo_weight[keep])
    report = make_derivatives(folder, tmp_path / "out", levels="t:3000:256")
    cap_share = float(np.mean(load_master(folder / "mesh.ply")[0][:, 2] >= 25.0))
    assert 0.5 * cap_share < report["master"]["bridged_vertex_share"] <= cap_share
    mask = cv2.imread(str(tmp_path / "out" / "mesh_t_bridged.png"), cv2.IMREAD_UNCHANGED)
    marked = report["levels"][0]["bake"]["bridged_share"]
    assert 0.02 < marked < 0.2 and (mask == 255).any()
