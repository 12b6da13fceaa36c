"""``qa.html``: the quality report as one self-contained page a conservator can read offline.

Every text from outside (title, identifier, collection, view names, notes) goes through
:func:`html.escape`; plots are PNGs inline as ``data:`` URIs; the page has no script, and its
Content-Security-Policy (``default-src 'none'``) forbids it any request, so it opens the same
from a disk, a USB stick or a web server, and a title of ``<script>`` is shown as text.
"""

from __future__ import annotations

import base64
import io
from collections.abc import Iterable, Sequence
from html import escape
from typing import Any

import numpy as np

__all__ = ["coverage_map_png", "render_qa_html"]

_CSS = """
body{font:14px/1.45 system-ui,-apple-system,'Segoe UI',sans-serif;margin:2em auto;max-width:1100px;color:#222;padding:0 1em}
h1{font-size:1.6em;margin-bottom:.2em}h2{font-size:1.2em;margin-top:1.8em;border-bottom:1px solid #ccc}
.ids{color:#555}.verdict{padding:.7em 1em;border-radius:6px;font-weight:600;margin:1em 0}
.ok{background:#e3f4e1;color:#1d5e1a}.bad{background:#fbe3e1;color:#8a1c12}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ddd;padding:.25em .6em;text-align:right}
th{background:#f4f4f4}td.l,th.l{text-align:left}.no{color:#8a1c12;font-weight:600}.yes{color:#1d5e1a}
.note{color:#555;font-style:italic}img{max-width:100%;border:1px solid #eee}
"""


def _png(fig: Any) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=96, bbox_inches="tight")
    import matplotlib.pyplot as plt

    plt.close(fig)
    return "data:image/png;base64," + base64.b64encode(buf.getvalue()).decode("ascii")


def _bars(labels: Sequence[str], series: dict[str, Sequence[float | None]], ylabel: str, limit: float | None) -> str:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(max(4.0, 0.5 * len(labels) + 2), 2.8))
    x = np.arange(len(labels))
    width = 0.8 / max(len(series), 1)
    for i, (name, vals) in enumerate(series.items()):
        ax.bar(x + i * width, [np.nan if v is None else v for v in vals], width, label=name)
    if limit is not None:
        ax.axhline(limit, color="#b33", lw=1, ls="--", label="threshold")
    ax.set_xticks(x + width * (len(series) - 1) / 2, labels, rotation=45 if len(labels) > 6 else 0, ha="right"
                  if len(labels) > 6 else "center")
    ax.set_ylabel(ylabel)
    ax.legend(fontsize=8)
    return _png(fig)


def coverage_map_png(points: np.ndarray, counts: np.ndarray, views: int) -> str:
    """A map of the object unrolled around its up axis (+y): azimuth across, height up; each place
    coloured by how many views saw it, red where none did (a bridged mesh region). ``points`` (N, 3)
    mm in the upright frame; ``counts`` (N,) int."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import BoundaryNorm, ListedColormap

    fig, ax = plt.subplots(figsize=(8, 3.2))
    az = np.degrees(np.arctan2(points[:, 0], points[:, 2]))
    order = np.argsort(counts, kind="stable")[::-1]  # unseen drawn last, on top
    top = max(views, 1)
    colours = ["#d62728", *plt.get_cmap("viridis")(np.linspace(0.15, 0.95, top))]
    cmap = ListedColormap(colours)
    norm = BoundaryNorm(np.arange(-0.5, top + 1.5), cmap.N)
    sc = ax.scatter(az[order], points[order, 1], c=counts[order], s=1.5, cmap=cmap, norm=norm, linewidths=0)
    cb = fig.colorbar(sc, ax=ax, ticks=np.arange(0, top + 1))
    cb.set_label("views that saw it (0: bridged)")
    ax.set_xlabel("azimuth around the up axis (deg, 0 = facing view 0)")
    ax.set_ylabel("height (mm)")
    ax.set_xlim(-180, 180)
    return _png(fig)


def _fmt(v: Any, digits: int = 3) -> str:
    if v is None:
        return "–"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if isinstance(v, float):
        return f"{v:.{digits}f}"
    return escape(str(v))


def _table(head: Sequence[str], rows: Iterable[Sequence[Any]], left: int = 1) -> str:
    th = "".join(f"<th class='l'>{escape(h)}</th>" if i < left else f"<th>{escape(h)}</th>" for i, h in enumerate(head))
    body = []
    for r in rows:
        cells = []
        for i, v in enumerate(r):
            cls = "l" if i < left else ""
            if isinstance(v, bool):
                cls += " yes" if v else " no"
            cells.append(f"<td class='{cls.strip()}'>{_fmt(v)}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table><tr>{th}</tr>{''.join(body)}</table>"


def render_qa_html(qa: dict[str, Any], coverage_png: str | None) -> str:
    """The page for a ``qa.json`` document (see :mod:`shared.publish.qa`); ``coverage_png`` a data URI."""
    obj = qa["object"]
    title = obj.get("title") or obj.get("identifier") or "Untitled object"
    verdict = qa["verdict"]
    parts = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        "<meta http-equiv='Content-Security-Policy' content=\"default-src 'none'; img-src data:; style-src 'unsafe-inline'\">",
        f"<title>Quality report: {escape(title)}</title><style>{_CSS}</style></head><body>",
        f"<h1>{escape(title)}</h1>",
        "<div class='ids'>" + " · ".join(f"{escape(k)}: <b>{escape(str(obj[k]))}</b>" for k in
                                         ("identifier", "collection", "kind") if obj.get(k)) + "</div>",
        f"<div class='verdict {'ok' if verdict['publishable'] else 'bad'}'>{escape(verdict['line'])}</div>",
    ]
    if verdict["reasons"]:
        parts.append("<ul>" + "".join(f"<li>{escape(r)}</li>" for r in verdict["reasons"]) + "</ul>")
    if qa.get("notes"):
        parts.append("<p class='note'>" + "<br>".join(escape(n) for n in qa["notes"]) + "</p>")

    parts.append("<h2>Calibration</h2>")
    cal = qa.get("calibration") or {}
    if "rms_px" in cal:
        rms = cal["rms_px"]
        parts.append(f"<p>Reprojection RMS: camera {_fmt(rms.get('camera'))} px, projector {_fmt(rms.get('projector'))} px"
                     f", stereo {_fmt(rms.get('stereo'))} px; {cal['poses_used']} of {cal['poses']} poses used. "
                     f"Board squares measured with the rig: RMS error {_fmt(cal.get('board_square_rms_error_pct'))} % "
                     f"of {_fmt(cal.get('board_square_size'))} {escape(str(cal.get('units', '')))}.</p>")
        per = cal.get("per_pose", [])
        if per:
            parts.append(f"<img alt='reprojection RMS per pose' src='{_bars([str(p['name']) for p in per], {'camera': [p['camera_rms_px'] for p in per], 'projector': [p['projector_rms_px'] for p in per]}, 'RMS (px)', qa['thresholds']['max_reprojection_px'])}'>")
            parts.append(_table(["pose", "used", "camera RMS px", "projector RMS px", "reason"],
                                [[p["name"], p["used"], p["camera_rms_px"], p["projector_rms_px"], p.get("reason")]
                                 for p in per]))
        board = cal.get("board_per_pose") or []
        if board:
            parts.append(_table(["pose", "mean square", "square RMS error %", "plane RMS"],
                                [[b.get("name"), b.get("square_mean"), b.get("square_rms_error_pct"), b.get("plane_rms")]
                                 for b in board]))
    else:
        parts.append(f"<p class='note'>{escape(str(cal.get('note', 'no calibration evidence')))}</p>")

    parts.append("<h2>Views</h2>")
    views = qa.get("views", [])
    if qa["object"].get("kind") == "merge":
        parts.append(f"<p>Method: {escape(str(qa.get('method')))}</p>")
        fits = [v for v in views if v.get("rms_mm") is not None]
        if fits:
            parts.append(f"<img alt='fit RMS per view' src='{_bars([str(v['name']) for v in fits], {'fit RMS': [v['rms_mm'] for v in fits]}, 'RMS (mm)', qa['thresholds']['max_fit_rms_mm'])}'>")
        parts.append(_table(["view", "registered", "points", "range valid share", "fit RMS mm", "overlap", "inlier share"],
                            [[v.get("name"), v.get("registered"), v.get("points"), v.get("range_valid_share"),
                              v.get("rms_mm"), v.get("overlap"), v.get("inlier_share")] for v in views]))
    else:
        parts.append(_table(["view", "points", "lit pixels", "points / lit", "decoded / lit", "camera"],
                            [[v.get("name"), v.get("points"), v.get("lit_pixels"), v.get("points_share_of_lit"),
                              v.get("decoded_share_of_lit"), "x".join(map(str, v.get("camera_size") or []))]
                             for v in views]))

    if qa["object"].get("kind") == "merge":
        parts.append("<h2>Registration</h2>")
        pairs = qa.get("pairs", [])
        if pairs:
            parts.append(_table(["pair", "overlap", "residual RMS mm", "inlier share"],
                                [["–".join(map(str, p.get("views", []))), p.get("overlap"), p.get("rms_mm"),
                                  p.get("inlier_share")] for p in pairs]))
        loop = qa.get("loop_closure")
        if isinstance(loop, dict):
            parts.append(f"<p>Loop closure (pairwise fits chained around the loop): "
                         f"{_fmt(loop.get('chained_pairwise_deg'))} deg, {_fmt(loop.get('chained_pairwise_mm'))} mm.</p>")
        axis = qa.get("turntable_axis")
        if isinstance(axis, dict) and axis.get("direction"):
            parts.append(f"<p>Turntable axis: direction ({', '.join(_fmt(v, 5) for v in axis['direction'])}), "
                         f"fit RMS {_fmt(axis.get('model_rms_mm'))} mm.</p>")
        flags = qa.get("quality_flags") or []
        if flags:
            parts.append(_table(["check", "ok", "detail"],
                                [[f["check"], f["ok"], ", ".join(f"{k} {v}" for k, v in f["detail"].items())]
                                 for f in flags]))
        else:
            parts.append("<p class='note'>The merge wrote no quality checks.</p>")

    parts.append("<h2>Noise and coverage</h2>")
    n = qa.get("noise") or {}
    if "median_mm" in n:
        parts.append(f"<p>Noise: points lie {_fmt(n['median_mm'])} mm (median; 90 % within {_fmt(n['p90_mm'])} mm) "
                     f"from the plane of their {n['neighbours']} nearest neighbours, over {n['sample']} of {n['points']} "
                     f"points; spacing {_fmt(n['spacing_mm'])} mm.</p>")
    cov = qa.get("coverage") or {}
    seen = cov.get("seen_by", {})
    total = max(sum(seen.values()), 1)
    parts.append(_table(["seen by views", f"{cov.get('of', '')}", "share"],
                        [[k, v, v / total] for k, v in seen.items()]))
    if cov.get("bridged_share") is not None:
        parts.append(f"<p>{100 * cov['bridged_share']:.1f} % of the mesh is bridged without data "
                     f"(no sample within {_fmt(cov.get('radius_mm'), 2)} mm).</p>")
    if coverage_png:
        parts.append(f"<img alt='coverage map' src='{coverage_png}'>")

    parts.append("<h2>Derivatives</h2>")
    dset = qa.get("derivative_set") or {}
    if dset.get("made_by"):
        made = f"Levels: {escape(dset['made_by'])}"
        if dset.get("colour"):
            made += f", colour baked from the {escape(dset['colour'])}"
        if dset.get("master_faces"):
            made += f", from a master mesh of {_fmt(dset['master_faces'])} faces"
        if isinstance(dset.get("bridged_vertex_share"), int | float):
            made += f" ({100 * dset['bridged_vertex_share']:.1f} % of its vertices bridged without data)"
        parts.append(f"<p>{made}.</p>")
    parts.append(_table(["quality", "file", "bytes", "faces", "points", "texture px", "within budget", "problems"],
                        [[d["quality"], d["file"], d["bytes"], d["faces"], d["points"], d["image_size"],
                          d["within_budget"], "; ".join(d["problems"])] for d in qa.get("derivatives", [])], left=2))
    parts.append("</body></html>")
    return "\n".join(parts)
