"""Train the octree cloud codec's model priors (writes ``shared/compress/_octree_prior.py``).

Usage: ``python -m tests.bench.train_cloud_prior [CLOUD.ply]``. Without an argument it trains on
the scene the table in the tree was trained on: the virtual rig's bunny scene at 1024x768, seed 0
(``graylight simulate --scene bunny --size 1024x768``), scanned in-process (737,863 points; not
the bench's cloud, which is a synthetic range image); a run from the tree of 538f101, where
the table was trained, rewrites the same table. The simulator and the scan have changed since
(a different training cloud), so a run today writes other values: retraining changes every
cloud stream's bytes, a codec change to measure on the bench before keeping it. With a PLY it trains on that cloud's ``x``, ``y``, ``z`` (millimetres). The cloud is cut into chunks as :func:`shared.compress.cloud.encode_cloud`
does and coded at 0.1 and 0.5 mm grids by the kernel's event pass with every model starting
from 1/2 (:func:`shared.compress._octree._events`, run from its source with each binary
event's models recorded in the kind array); the ones and events of every model, pooled over
both grids, are summed per group (:data:`~shared.compress._octree_prior.PRIOR_SHIFTS`) and a
group's prior is ``round(2048 + 0.5 * ((n1 + 0.4) / (n + 0.8) * 4096 - 2048))``.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

import numpy as np

from shared.compress import _octree, _octree_ctx, _rans
from shared.compress.cloud import chunk_points
from shared.formats.ply import iter_ply_records
from shared.scan.pipeline import scan
from shared.sim.simulate import simulate_named

SHIFTS = (3, 0, 0, 0, 9, 0, 0, 0, 0, 0, 0)


def _drop_import(src: str, module: str) -> str:
    """``src`` without its (parenthesised) ``from module import ...`` statement."""
    i0 = src.index(f"from {module} import (")
    return src[:i0] + src[src.index(")\n", i0) + 2 :]


def _uncached(src: str) -> str:
    """``src`` with its kernels compiled without numba's cache (source run from text has no file
    to cache beside): the ``shared.core.jit`` decorators it imports, with ``cache=False``."""
    lines = [ln for ln in src.splitlines() if ln.startswith("from shared.core.jit import ")]
    assert lines and "cache=True" not in src
    for line in lines:
        names = [n.strip() for n in line.split(" import ", 1)[1].split(",")]
        defs = "\n".join(f"{n} = functools.partial(_jit.{n}, cache=False)" for n in names)
        src = src.replace(line, f"import functools\nfrom shared.core import jit as _jit\n{defs}", 1)
    return src


def _kernels() -> dict:
    """The kernels' source run with every binary event's models packed into its ``nb`` entry
    (int64: kind + 8 * (A + B << 20 + C << 40)) and the initial states passed in."""
    rs = _uncached(Path(_rans.__file__).read_text())
    rns: dict = {"__name__": "train_rans"}
    exec(compile(rs, "train_rans", "exec"), rns)
    # the map and contexts (_octree_ctx), then the chunk coder, in one namespace: the latter's
    # imports of the rANS coder and of the former left out
    ctx = _drop_import(Path(_octree_ctx.__file__).read_text(), "shared.compress._rans")
    s = Path(_octree.__file__).read_text()
    for mod in ("shared.compress._octree_ctx", "shared.compress._rans"):
        s = _drop_import(s, mod)
    s = _uncached(ctx + "\n" + s.replace("from __future__ import annotations\n", "", 1))
    for a, b in (
        ("def _events(levels, starts, counts, depth, chan, log2d, tab, val, nb):",
         "def _events(levels, starts, counts, depth, chan, log2d, tab, val, nb, prior):"),
        ("    prior = _prior_states()\n    for d in range(depth):", "    for d in range(depth):"),
        ("    nb[n] = kind\n    model_update(models, ctx, bit)", "    nb[n] = kind + 8 * ctx\n    model_update(models, ctx, bit)"),
        ("    nb[n] = kind\n    _learn(", "    nb[n] = kind + 8 * (ca + (cb << 20) + (cc << 40))\n    _learn("),
    ):
        assert a in s, a
        s = s.replace(a, b, 1)
    ns = {"__name__": "train_octree"}
    ns.update({k: v for k, v in rns.items() if not k.startswith("__")})
    exec(compile(s, "train_octree", "exec"), ns)
    return ns


def counts(rec: np.ndarray, ns: dict) -> tuple[np.ndarray, np.ndarray]:
    """Ones and events (N_MODELS,) float64 of every model over the chunks of ``rec`` at 0.1 and 0.5 mm."""
    nm = ns["N_MODELS"]
    ones = np.zeros(nm)
    tot = np.zeros(nm)
    flat = np.full(nm, 1 << 15, np.uint32)
    per = chunk_points(len(rec))
    for g in (0.1, 0.5):
        for s in range(0, len(rec), per):
            r = rec[s : s + per]
            q = np.floor(np.stack([r["x"], r["y"], r["z"]], 1).astype(np.float64) / g).astype(np.int64)
            q -= q.min(0)
            depth = max(1, int(q.max()).bit_length())
            codes = np.unique(ns["morton"](q))
            levels, starts = ns["_levels"](codes, depth)
            cap = 8 * starts[depth] + 4 * len(codes) + 4096
            tab = np.empty(cap, np.int8)
            val = np.empty(cap, np.int16)
            nb = np.empty(cap, np.int64)
            nv = len(codes)
            n = ns["_events"](levels, starts, np.ones(nv, np.int64), depth, np.zeros((nv, 0), np.int64), np.zeros(0, np.int64), tab, val, nb, flat)
            b = tab[:n] == ns["BIN"]
            bit = (val[:n][b] & 1).astype(np.float64)
            kind = nb[:n][b] & 7
            pk = nb[:n][b] >> 3
            mixed = pk >= (1 << 20)  # a mixed event's B model is never model 0
            a = np.where(mixed, pk & 0xFFFFF, pk)
            for c, m in ((a, np.ones(len(a), bool)), ((pk >> 20) & 0xFFFFF, mixed), ((pk >> 40) & 0xFFFFF, mixed)):
                np.add.at(ones, c[m], bit[m])
                np.add.at(tot, c[m], 1)
            assert kind.max() <= 4
    return ones, tot


def training_cloud(ply: Path | None = None) -> np.ndarray:
    """The records of ``ply``, or of the bunny scene scanned by the virtual rig (see above)."""
    if ply is not None:
        return np.concatenate(list(iter_ply_records(ply, 1 << 22)))
    with tempfile.TemporaryDirectory() as tmp:
        simulate_named("bunny", Path(tmp) / "capture", size=(1024, 768), seed=0)
        scan(Path(tmp) / "capture", Path(tmp) / "scan")
        return training_cloud(Path(tmp) / "scan" / "cloud.ply")


def main() -> None:
    ns = _kernels()
    ones, tot = counts(training_cloud(Path(sys.argv[1]) if len(sys.argv) > 1 else None), ns)
    bounds = [ns[k] for k in ("C_BIT", "C_SINGLE", "C_X", "C_Y", "C_Z", "B_X", "B_Y", "C3_X", "C3_Y", "B_SINGLE", "C3_SINGLE", "N_MODELS")]
    p12 = []
    for a, b, s in zip(bounds[:-1], bounds[1:], SHIFTS, strict=True):
        k = np.arange(b - a) >> s
        tg = np.bincount(k, tot[a:b])
        og = np.bincount(k, ones[a:b])
        p12.append(np.round(2048 + 0.5 * ((og + 0.4) / (tg + 0.8) * 4096 - 2048)).astype(np.int64))
    p = np.concatenate(p12)
    path = Path(_octree.__file__).with_name("_octree_prior.py")
    src = path.read_text()
    head = src[: src.index("PRIOR_BOUNDS = ")]
    rows = [", ".join(str(int(v)) for v in p[i : i + 24]) for i in range(0, len(p), 24)]
    body = "\n".join(f"    {r}," for r in rows)
    path.write_text(
        head
        + f"PRIOR_BOUNDS = np.array(({', '.join(map(str, bounds))}), np.int64)\n"
        + "#: Per region, how many low bits of a context's offset its group ignores.\n"
        + f"PRIOR_SHIFTS = np.array(({', '.join(map(str, SHIFTS))}), np.int64)\n"
        + "#: Per group, region after region, the 12-bit probability of a one.\n"
        + f"PRIOR_P12 = np.array((\n{body}\n), np.int16)\n"
    )


if __name__ == "__main__":
    main()
