"""The web viewer on octree-coded tiles (``node_codec="octree"``), in a real headless Chromium.

The viewer's own decoder worker (``assets/decoder.js``) decodes every node of the same scan's
plain and octree-coded tiles; the decoded nodes must hold the same points (positions, colours,
sizes and normals, as multisets: a coded node holds its points in octree order). The decode
speed in the browser is printed (points per second in the worker, and the plain decoder's
beside it), never asserted. The whole viewer then draws the coded tiles like the plain ones.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from fastapi import FastAPI
from fastapi.staticfiles import StaticFiles

from services.viewer import routes
from shared.compress import tilenode
from shared.formats.potree import open_tiles
from shared.render.octree import build_tiles
from tests.support.clouds import synthetic_scan
from tests.support.viewer_browser import Page, Server, built_viewer, chromium

pytestmark = [pytest.mark.xdist_group("viewer"), pytest.mark.slow]

POINTS = 300_000


@pytest.fixture(scope="module")
def tile_sets(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("viewer-tilenode")
    cloud = synthetic_scan(root / "scan.ply", POINTS, seed=21)
    build_tiles(cloud, root / "plain", workers=2, max_leaf=5000)
    build_tiles(cloud, root / "octree", workers=2, max_leaf=5000, node_codec="octree")
    return {"root": root, "plain": root / "plain", "octree": root / "octree"}


@pytest.fixture(scope="module")
def server(tile_sets: dict[str, Path]) -> Iterator[Server]:
    built_viewer()
    app = FastAPI()
    app.include_router(routes.create_router())
    app.mount("/static", StaticFiles(directory=tile_sets["root"]), name="static")
    with Server(app) as s:
        yield s


@pytest.fixture(scope="module")
def browser() -> Iterator[object]:
    with chromium() as b:
        yield b


def _node_table(plain: Path, coded: Path) -> list[dict]:
    tp, tc = open_tiles(plain), open_tiles(coded, decoders=tilenode.DECODERS)
    return [
        {"name": nm, "count": n.num_points, "plain": [n.byte_offset, n.byte_size],
         "coded": [tc.nodes[nm].byte_offset, tc.nodes[nm].byte_size]}
        for nm, n in tp.nodes.items() if n.num_points
    ]  # fmt: skip


def _params(meta: dict) -> dict:
    """The decoder parameters the viewer's potree.ts derives for these tiles (local frame at the box minimum)."""
    offsets, at = {}, 0
    for a in meta["attributes"]:
        offsets[a["name"]] = at
        at += a["size"]
    return {
        "layout": {"stride": at, "position": offsets["position"],
                   "color": {"offset": offsets["rgb"], "type": "uint16", "shift": 8},
                   "size": {"offset": offsets["size"], "type": "float"}, "normal": offsets["NormalX"]},
        "scale": meta["scale"],
        "gridOffset": [meta["offset"][k] - meta["boundingBox"]["min"][k] for k in range(3)],
    }  # fmt: skip


# Runs in the page: the viewer's decoder worker decodes every node both ways; equality as
# sorted per-point keys (float bit patterns and colour bytes). Keeps the worker and the files
# in ``window.__tn`` for the timed passes.
_DECODE_BOTH = r"""
async ({ nodes, params }) => {
  const worker = new Worker("/viewer/assets/decoder.js", { type: "module" });
  const pending = new Map();
  let next = 0;
  worker.onmessage = (e) => { pending.get(e.data.id)(e.data); pending.delete(e.data.id); };
  const call = (buffer, count, encoding) => new Promise((resolve) => {
    const id = next++;
    pending.set(id, resolve);
    worker.postMessage({ id, buffer, count, params: { ...params, encoding } }, [buffer]);
  });
  const plain = await (await fetch("/static/plain/octree.bin")).arrayBuffer();
  const coded = await (await fetch("/static/octree/octree.bin")).arrayBuffer();
  window.__tn = { call, nodes, files: { DEFAULT: plain, GRAYLIGHT_OCTREE: coded } };
  const keys = (p) => {
    const pos = new Uint32Array(p.positions.buffer), nrm = new Uint32Array(p.normals.buffer);
    const siz = new Uint32Array(p.sizes.buffer), out = new Array(p.count);
    for (let i = 0; i < p.count; i++) {
      out[i] = [pos[3 * i], pos[3 * i + 1], pos[3 * i + 2], p.colors[3 * i], p.colors[3 * i + 1], p.colors[3 * i + 2],
                siz[i], nrm[3 * i], nrm[3 * i + 1], nrm[3 * i + 2]].join(",");
    }
    return out.sort();
  };
  const mismatched = [];
  let points = 0;
  for (const n of nodes) {
    const a = await call(plain.slice(n.plain[0], n.plain[0] + n.plain[1]), n.count, "DEFAULT");
    const b = await call(coded.slice(n.coded[0], n.coded[0] + n.coded[1]), n.count, "GRAYLIGHT_OCTREE");
    if (a.error || b.error) { mismatched.push(`${n.name}: ${a.error || b.error}`); continue; }
    const ka = keys(a.points), kb = keys(b.points);
    if (b.points.count !== n.count || ka.length !== kb.length || ka.some((k, i) => k !== kb[i])) mismatched.push(n.name);
    points += b.points.count;
  }
  const broken = nodes.find((n) => n.count > 100);
  const bad = await call(coded.slice(broken.coded[0], broken.coded[0] + broken.coded[1] - 9), broken.count, "GRAYLIGHT_OCTREE");
  const empty = await call(new ArrayBuffer(0), 0, "GRAYLIGHT_OCTREE");
  return { mismatched, points, badError: bad.error ?? null, emptyCount: empty.error ?? empty.points.count, plainBytes: plain.byteLength, codedBytes: coded.byteLength };
}
"""

# Timed passes over every node: one node at a time (the sum of the worker's own decode times),
# or every node in flight at once as the viewer loads them (wall time, messaging included).
_TIMED = r"""
async ({ encoding, reps, inFlight }) => {
  const { call, nodes, files } = window.__tn;
  const span = (n) => (encoding === "DEFAULT" ? n.plain : n.coded);
  const part = (n) => files[encoding].slice(span(n)[0], span(n)[0] + span(n)[1]);
  let best = Infinity;
  for (let r = 0; r < reps; r++) {
    let ms = 0;
    if (inFlight) {
      const t0 = performance.now();
      await Promise.all(nodes.map((n) => call(part(n), n.count, encoding)));
      ms = performance.now() - t0;
    } else {
      for (const n of nodes) ms += (await call(part(n), n.count, encoding)).ms;
    }
    best = Math.min(best, ms);
  }
  return best;
}
"""


def _cpu_seconds_of_children() -> float:
    """User + system CPU seconds of this process's descendants (Playwright's driver, Chromium's
    processes), from /proc: the decode's CPU cost, whatever else loads the machine."""
    parent: dict[int, int] = {}
    ticks: dict[int, int] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rsplit(")", 1)[1].split()
        except OSError:
            continue
        pid = int(stat.parent.name)
        parent[pid] = int(fields[1])
        ticks[pid] = int(fields[11]) + int(fields[12])
    me, total = os.getpid(), 0
    for pid, t in ticks.items():
        p = pid
        while p in parent and p not in (0, 1, me):
            p = parent[p]
        if p == me and pid != me:
            total += t
    return total / os.sysconf("SC_CLK_TCK")


def test_worker_decodes_coded_nodes_to_the_plain_nodes_points(server, browser, tile_sets) -> None:
    nodes = _node_table(tile_sets["plain"], tile_sets["octree"])
    meta = json.loads((tile_sets["plain"] / "metadata.json").read_text())
    page = Page(browser, f"{server.url}/viewer/?ui=0")
    reps = 5
    try:
        out = page.page.evaluate(_DECODE_BOTH, {"nodes": nodes, "params": _params(meta)})
        assert out["mismatched"] == []
        timing = {}
        for encoding in ("GRAYLIGHT_OCTREE", "DEFAULT"):
            c0 = _cpu_seconds_of_children()
            ms = page.page.evaluate(_TIMED, {"encoding": encoding, "reps": reps, "inFlight": False})
            cpu = (_cpu_seconds_of_children() - c0) / reps
            flight = page.page.evaluate(_TIMED, {"encoding": encoding, "reps": reps, "inFlight": True})
            timing[encoding] = (ms, cpu, flight)
    finally:
        page.close()
    assert out["points"] == meta["points"] == sum(n["count"] for n in nodes)
    assert out["badError"] and "octree-coded node" in out["badError"]
    assert out["emptyCount"] == 0  # an empty node (no bytes) decodes to no points
    n = out["points"]
    lines = [f"\nbrowser decode of {n} points in {len(nodes)} nodes (Chromium, one decoder worker, best of {reps}; "
             f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} cores):"]  # fmt: skip
    for encoding, label in (("GRAYLIGHT_OCTREE", "octree-coded"), ("DEFAULT", "plain")):
        ms, cpu, flight = timing[encoding]
        lines.append(f"  {label:12s} {n / ms / 1e3:6.2f} M points/s node by node in the worker ({ms:.0f} ms; "
                     f"{cpu * 1e3:.0f} ms CPU of Chromium a pass, {n / max(cpu, 1e-3) / 1e6:.2f} M points/CPU-s), "
                     f"{n / flight / 1e3:.2f} M points/s with every node in flight")  # fmt: skip
    lines.append(f"  octree.bin {out['plainBytes'] / n:.2f} -> {out['codedBytes'] / n:.2f} bytes a point "
                 f"({out['plainBytes'] / out['codedBytes']:.2f}x smaller)")  # fmt: skip
    print("\n".join(lines))
    assert out["codedBytes"] < out["plainBytes"] / 2


def test_viewer_draws_coded_tiles_like_plain_ones(server, browser, tile_sets) -> None:
    total = open_tiles(tile_sets["plain"]).points
    images, drawn = {}, {}
    for name in ("plain", "octree"):
        page = Page(browser, f"{server.url}/viewer/?tiles=/static/{name}/&ui=0&edl=0&budget={10 * total}", size=(480, 360))
        try:
            state = page.wait_idle()
            assert state["error"] is None, state["error"]
            # Every node in view drawn (the budget is no limit; nodes outside the frustum are culled).
            assert state["decoderWorkers"] == 2 and 0.9 * total < state["drawnPoints"] <= total
            drawn[name] = (state["drawnPoints"], state["loadedNodes"])
            assert state["hasColor"] and state["hasSize"]
            images[name] = page.capture().astype(int)
            assert not [e for e in page.errors if "graylight viewer" in e], page.errors
        finally:
            page.close()
    assert drawn["octree"] == drawn["plain"]
    differ = (np.abs(images["plain"] - images["octree"]).sum(axis=2) > 30).mean()
    # The same points, drawn in another order within a node: equal-depth ties may differ in a few pixels.
    assert differ < 0.01, f"{differ:.2%} of the pixels differ"
    bg = np.array([0.08, 0.09, 0.11]) * 255
    lit = (np.abs(images["octree"] - bg).sum(axis=2) > 30).mean()
    assert lit > 0.25, f"only {lit:.0%} of the frame shows points"
