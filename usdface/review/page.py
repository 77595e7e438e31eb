"""The review page: one self-contained HTML file (plotly.js inlined, mesh data embedded) showing the generic
and the personalized face side by side, with a slider per shape, presets, a change heat map, landmarks,
playback and the fit's figures.

Arrays in, HTML text out; no USD here (:mod:`usdface.review.collect` reads the files). The rendering is
plotly's ``Mesh3d`` (WebGL, lit, orbitable); the only hand-written code is ``viewer.js`` (next to this
module), which blends the embedded shape deltas and calls ``Plotly.restyle``.

Data conventions: ``neutral[n, 3]`` metres, Y up, the face looking down +Z; ``deltas[K, n, 3]`` metres;
``weights[F, K]`` in [0, 1]; ``heat[n]`` metres. In the page, shape deltas are stored sparse (only the
vertices a shape moves by more than :data:`SPARSE_TOLERANCE_M`) and quantized to int16 with one scale per
shape (step = largest component / 32767, well below 0.01 mm for face shapes); sequence weights as uint8.
"""

from __future__ import annotations

import base64
import html
import json
from dataclasses import dataclass, field
from importlib import resources

import numpy as np

__all__ = ["ReviewMesh", "Sequence", "ReviewData", "build_review_html", "encode_sparse_deltas",
           "decode_sparse_deltas", "framed_ranges", "PRESETS", "SPARSE_TOLERANCE_M"]

#: A vertex offset shorter than this is left out of a shape's sparse deltas in the page (metres; 0.01 mm,
#: far below what a screen shows, and below the float32 noise of a cm-scale avatar's BlendShape offsets).
SPARSE_TOLERANCE_M = 1e-5

#: Named poses: {preset: {shape: weight}}.
PRESETS = {
    "smile": {"mouthSmileLeft": 1.0, "mouthSmileRight": 1.0, "cheekSquintLeft": 0.4, "cheekSquintRight": 0.4},
    "jaw open": {"jawOpen": 1.0},
    "blink": {"eyeBlinkLeft": 1.0, "eyeBlinkRight": 1.0},
    "pucker": {"mouthPucker": 1.0},
    "brows up": {"browInnerUp": 1.0, "browOuterUpLeft": 1.0, "browOuterUpRight": 1.0},
}

_COLORS = {"skin": "#d8b19a", "mouth": "#c07e7e", "eye": "#eeeeea"}


@dataclass
class ReviewMesh:
    """One mesh of the avatar: ``neutral[n, 3]``, ``triangles[t, 3]``, shape ``names[K]`` and the deltas of
    both variants (``generic[K, n, 3]``, ``personalized[K, n, 3]``; both empty for a static mesh such as an
    eye bound to the skeleton only); ``heat[n]`` metres (optional) and ``landmarks[m]`` vertex indices
    (optional)."""

    name: str
    neutral: np.ndarray
    triangles: np.ndarray
    names: list[str] = field(default_factory=list)
    generic: np.ndarray | None = None
    personalized: np.ndarray | None = None
    heat: np.ndarray | None = None
    landmarks: np.ndarray | None = None

    @property
    def role(self) -> str:
        low = self.name.lower()
        if "eye" in low:
            return "eye"
        if any(s in low for s in ("mouth", "teeth", "tongue", "gum")):
            return "mouth"
        return "skin"


@dataclass
class Sequence:
    """A playable sequence: ``weights[F, K]`` for ``names[K]`` at ``times[F]`` seconds, with frame labels."""

    title: str
    names: list[str]
    weights: np.ndarray
    times: np.ndarray
    labels: list[str] = field(default_factory=list)


@dataclass
class Listing:
    """A list of names for a table cell: its count and the first :data:`LISTING_SHOWN` in the cell, the whole
    list one click away (an HTML ``<details>``). dev3's review listed the 46 Mouth shapes left generic on one
    line of the table (stop 43)."""

    names: list[str]

    def __str__(self) -> str:
        shown = ", ".join(self.names[:LISTING_SHOWN])
        more = len(self.names) - LISTING_SHOWN
        return f"{len(self.names)}: {shown}" + (f" (+{more} more)" if more > 0 else "")

    def html(self) -> str:
        if len(self.names) <= LISTING_SHOWN:
            return html.escape(str(self))
        return (f"<details><summary>{html.escape(str(self))}</summary>"
                f"{html.escape(', '.join(self.names))}</details>")


#: The names a :class:`Listing` shows before its count of more (the rest in its details).
LISTING_SHOWN = 5


@dataclass
class ReviewData:
    """Everything the page shows. ``tables``: [(title, [(label, value), ...])] of text figures (a value a
    ``str`` or a :class:`Listing`); ``errors``: optional eq. 5 table {"labels": [F], "columns": {name: [F]
    mm}}."""

    title: str
    meshes: list[ReviewMesh]
    sequences: list[Sequence] = field(default_factory=list)
    tables: list[tuple[str, list[tuple[str, str | Listing]]]] = field(default_factory=list)
    errors: dict | None = None
    notes: list[str] = field(default_factory=list)
    #: ``(lo[3], hi[3])`` the views are cut to, from the full meshes (:func:`framed_ranges`; the meshes may
    #: be cut to it since); ``None``: computed from ``meshes``
    view_box: tuple | None = None


def _b64(array: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(array).tobytes()).decode("ascii")


def encode_sparse_deltas(deltas: np.ndarray, tolerance: float = SPARSE_TOLERANCE_M) -> list[dict]:
    """Shape deltas ``deltas[K, n, 3]`` (metres) -> one dict per shape: ``idx`` (base64 uint16, or uint32 when
    n >= 65536, the moved vertices), ``q`` (base64 int16 [m, 3]) and ``s`` (float: metres per step), so that
    ``delta[idx] = q * s``. Vertices moved by less than ``tolerance`` are dropped."""
    deltas = np.asarray(deltas, dtype=np.float64)
    n = deltas.shape[1] if deltas.ndim == 3 else 0
    idx_type = np.uint16 if n < 65536 else np.uint32
    out = []
    for d in deltas:
        moved = np.flatnonzero(np.linalg.norm(d, axis=1) > tolerance)
        vals = d[moved]
        top = float(np.abs(vals).max()) if vals.size else 0.0
        scale = top / 32767.0 if top > 0 else 1.0
        q = np.round(vals / scale).astype(np.int16)
        out.append({"idx": _b64(moved.astype(idx_type)), "q": _b64(q), "s": scale, "m": int(moved.size)})
    return out


def decode_sparse_deltas(encoded: list[dict], n: int) -> np.ndarray:
    """Inverse of :func:`encode_sparse_deltas` (what the page's script computes): ``deltas[K, n, 3]``."""
    idx_type = np.uint16 if n < 65536 else np.uint32
    out = np.zeros((len(encoded), n, 3))
    for k, e in enumerate(encoded):
        idx = np.frombuffer(base64.b64decode(e["idx"]), dtype=idx_type).astype(np.int64)
        q = np.frombuffer(base64.b64decode(e["q"]), dtype=np.int16).reshape(-1, 3)
        out[k, idx] = q * e["s"]
    return out


#: Landmark markers float this far (metres) off the surface along the neutral's normal, so the depth test
#: does not cut them in half.
LANDMARK_LIFT_M = 0.0015


def _landmark_offsets(m: ReviewMesh) -> np.ndarray:
    from ..mesh import vertex_normals

    idx = np.asarray(m.landmarks, dtype=np.int64)
    return vertex_normals(m.neutral, m.triangles)[idx] * LANDMARK_LIFT_M


def _payload(data: ReviewData) -> dict:
    names = list(dict.fromkeys(n for m in data.meshes for n in m.names))
    meshes = []
    for m in data.meshes:
        mesh = {"name": m.name, "role": m.role, "n": int(len(m.neutral)),
                "neutral": _b64(np.asarray(m.neutral, dtype=np.float32)),
                "shapes": [names.index(s) for s in m.names]}
        if m.names:
            mesh["generic"] = encode_sparse_deltas(m.generic)
            # personalized = generic + change; the change is zero away from the face: stored sparse too
            mesh["change"] = encode_sparse_deltas(np.asarray(m.personalized) - np.asarray(m.generic))
        if m.heat is not None:
            mesh["heat"] = _b64(np.asarray(m.heat, dtype=np.float32) * np.float32(1000.0))  # mm
        if m.landmarks is not None and len(m.landmarks):
            mesh["landmarks"] = [int(i) for i in m.landmarks]
            mesh["lmOffset"] = [round(float(v), 6) for v in _landmark_offsets(m).ravel()]
        meshes.append(mesh)
    sequences = []
    for s in data.sequences:
        cols = [names.index(n) if n in names else -1 for n in s.names]
        w = np.zeros((len(s.weights), len(names)))
        for j, c in enumerate(cols):
            if c >= 0:
                w[:, c] = s.weights[:, j]
        sequences.append({"title": s.title, "frames": int(len(w)),
                          "times": [round(float(t), 4) for t in s.times],
                          "labels": list(s.labels),
                          "w": _b64(np.round(np.clip(w, 0.0, 1.0) * 255.0).astype(np.uint8))})
    presets = {p: {k: v for k, v in shapes.items() if k in names} for p, shapes in PRESETS.items()}
    return {"names": names, "meshes": meshes, "sequences": sequences,
            "presets": {p: v for p, v in presets.items() if v}}


def framed_ranges(meshes) -> tuple[np.ndarray, np.ndarray] | None:
    """``(lo[3], hi[3])`` the page's view is cut to when a mesh's shapes move less than half of it
    (:func:`usdface.render.moving_region`: a face on a head-and-body mesh, drawn as the whole body, was a
    few per cent of the view): the box of its moving vertices and of the other meshes, 10 % larger; ``None``
    when every mesh moves mostly (the view shows everything, as before)."""
    from ..render import moving_region

    parts, cropped = [], False
    for m in meshes:
        region = moving_region(m.generic) if m.names and m.generic is not None else None
        cropped |= region is not None
        parts.append(np.asarray(m.neutral)[region] if region is not None else np.asarray(m.neutral))
    if not cropped:
        return None
    points = np.concatenate(parts)
    lo, hi = points.min(axis=0), points.max(axis=0)
    pad = 0.05 * float((hi - lo).max() or 1.0)
    return lo - pad, hi + pad


def _figure(data: ReviewData):
    import plotly.graph_objects as go

    fig = go.Figure()
    lighting = {"ambient": 0.42, "diffuse": 0.8, "specular": 0.12, "roughness": 0.6, "fresnel": 0.15}
    for scene, variant in (("scene", "generic"), ("scene2", "personalized")):
        for m in data.meshes:
            p = np.asarray(m.neutral, dtype=np.float32)
            t = np.asarray(m.triangles, dtype=np.uint16 if len(p) < 65536 else np.uint32)
            fig.add_trace(go.Mesh3d(
                x=p[:, 0], y=p[:, 1], z=p[:, 2], i=t[:, 0], j=t[:, 1], k=t[:, 2],
                name=f"{m.name} ({variant})",
                color=_COLORS[m.role], flatshading=False, lighting=lighting,
                lightposition={"x": 2e4, "y": 3e4, "z": 6e4}, hoverinfo="skip", showscale=False,
                scene=scene, colorbar={"title": {"text": "mm"}, "len": 0.6, "x": 0.96, "xanchor": "right"}))
        for m in data.meshes:
            if m.landmarks is not None and len(m.landmarks):
                lm = np.asarray(m.landmarks, dtype=np.int64)
                q = (m.neutral[lm] + _landmark_offsets(m)).astype(np.float32)
                fig.add_trace(go.Scatter3d(x=q[:, 0], y=q[:, 1], z=q[:, 2], mode="markers", scene=scene,
                                           name=f"{m.name} landmarks ({variant})", hoverinfo="skip",
                                           marker={"size": 2.5, "color": "#2f7df6"}))
    axis = {"visible": False, "showspikes": False}
    framed = data.view_box if data.view_box is not None else framed_ranges(data.meshes)
    camera = {"up": {"x": 0, "y": 1, "z": 0}, "eye": {"x": 0.0, "y": 0.05, "z": 1.5},
              "center": {"x": 0, "y": 0, "z": 0}, "projection": {"type": "perspective"}}
    scene = {"xaxis": axis, "yaxis": axis, "zaxis": axis, "aspectmode": "data", "camera": camera,
             "dragmode": "orbit", "bgcolor": "#1d2127"}
    if framed is not None:            # the moving part of a larger still mesh: the rest is cut off
        lo, hi = framed
        size = hi - lo
        scene.update({f"{c}axis": {**axis, "range": [float(lo[i]), float(hi[i])], "autorange": False}
                      for i, c in enumerate("xyz")})
        scene.update(aspectmode="manual",
                     aspectratio={c: float(size[i] / size.max()) for i, c in enumerate("xyz")})
    fig.update_layout(
        scene={**scene, "domain": {"x": [0.0, 0.5], "y": [0.0, 1.0]}},
        scene2={**scene, "domain": {"x": [0.5, 1.0], "y": [0.0, 1.0]}},
        margin={"l": 0, "r": 0, "t": 28, "b": 0}, paper_bgcolor="#1d2127", showlegend=False,
        modebar={"orientation": "v", "bgcolor": "rgba(0,0,0,0)"},
        font={"color": "#dddddd"},
        annotations=[{"text": "generic", "x": 0.25, "y": 1.0, "xref": "paper", "yref": "paper",
                      "showarrow": False, "yanchor": "bottom", "font": {"size": 15}},
                     {"text": "personalized", "x": 0.75, "y": 1.0, "xref": "paper", "yref": "paper",
                      "showarrow": False, "yanchor": "bottom", "font": {"size": 15}}])
    return fig


def _tables_html(data: ReviewData) -> str:
    parts = []
    for title, rows in data.tables:
        body = "".join(f"<tr><th>{html.escape(str(k))}</th>"
                       f"<td>{v.html() if isinstance(v, Listing) else html.escape(str(v))}</td></tr>"
                       for k, v in rows)
        parts.append(f"<table class='figs'><caption>{html.escape(title)}</caption>{body}</table>")
    if data.errors:
        cols = list(data.errors["columns"])
        head = "".join(f"<th>{html.escape(c)}</th>" for c in ["test expression", *cols])
        rows = []
        for f, label in enumerate(data.errors["labels"]):
            cells = "".join(f"<td>{data.errors['columns'][c][f]:.3f}</td>" for c in cols)
            rows.append(f"<tr><th>{html.escape(str(label))}</th>{cells}</tr>")
        means = "".join(f"<td><b>{np.mean(data.errors['columns'][c]):.3f}</b></td>" for c in cols)
        rows.append(f"<tr><th>mean</th>{means}</tr>")
        parts.append(f"<table class='figs'><caption>{html.escape(data.errors.get('title', 'errors'))}"
                     f"</caption><tr>{head}</tr>{''.join(rows)}</table>")
    notes = "".join(f"<li>{html.escape(n)}</li>" for n in data.notes)
    if notes:
        parts.append(f"<ul class='notes'>{notes}</ul>")
    return "\n".join(parts)


_STYLE = """
body{margin:0;overflow-x:hidden;background:#15181d;color:#ddd;font:13px/1.4 system-ui,sans-serif}
#usdface-app{display:flex;height:82vh}
#usdface-panel{width:270px;overflow-x:hidden;overflow-y:auto;padding:6px 10px;border-right:1px solid #333;
  flex:none}
#usdface-plotwrap{flex:1;min-width:0;height:82vh}
#usdface-plotwrap>div{height:100%}
#usdface-panel select{max-width:250px}
#usdface-panel h3{margin:10px 0 4px;font-size:13px;color:#9cf}
#usdface-panel button{margin:2px;background:#2a3038;color:#ddd;border:1px solid #444;border-radius:3px;
  cursor:pointer}
#usdface-panel label.sl{display:flex;align-items:center;gap:4px;font-size:11px}
#usdface-panel label.sl span{width:118px;overflow:hidden;text-overflow:ellipsis;white-space:nowrap}
#usdface-panel label.sl input{width:90px}
#usdface-status{position:fixed;right:6px;bottom:4px;font-size:11px;color:#7a7}
#usdface-figures{display:flex;flex-wrap:wrap;gap:18px;padding:10px 14px}
table.figs{border-collapse:collapse;font-size:12px}
table.figs caption{text-align:left;font-weight:bold;color:#9cf;padding:4px 0}
table.figs th,table.figs td{border:1px solid #333;padding:2px 6px;text-align:left;font-weight:normal}
table.figs td{font-variant-numeric:tabular-nums}
h1{font-size:16px;margin:6px 12px}
"""


#: Any uncaught error or rejected promise ends up in the status element (tests read it with --dump-dom).
_ERROR_HOOK = ("function usdfaceFail(m){var s=document.getElementById('usdface-status');"
               "s.textContent='error: '+m;s.style.color='#f66';}"
               "window.addEventListener('error',function(e){usdfaceFail(e.message);});"
               "window.addEventListener('unhandledrejection',function(e){"
               "usdfaceFail(e.reason&&e.reason.message?e.reason.message:String(e.reason));});")


def build_review_html(data: ReviewData) -> str:
    """The complete page (plotly.js inlined: no network needed to view it)."""
    import plotly.io as pio

    fig = _figure(data)
    script = resources.files("usdface.review").joinpath("viewer.js").read_text(encoding="utf-8")
    payload = json.dumps(_payload(data), separators=(",", ":"))
    post = f"window.USDFACE_DATA = {payload};\n{script}\nusdfaceStart('{{plot_id}}');"
    body = pio.to_html(fig, include_plotlyjs=True, full_html=False, div_id="usdface-plot",
                       post_script=post, config={"responsive": True, "displaylogo": False},
                       default_width="100%", default_height="100%")
    title = html.escape(data.title)
    return ("<!DOCTYPE html>\n<html><head><meta charset='utf-8'>"
            f"<title>{title}</title><style>{_STYLE}</style></head><body>"
            "<div id='usdface-status'>loading</div>"
            f"<script>{_ERROR_HOOK}</script>"
            f"<h1>{title}</h1><div id='usdface-app'><div id='usdface-panel'></div>"
            f"<div id='usdface-plotwrap'>{body}</div></div>"
            f"<div id='usdface-figures'>{_tables_html(data)}</div></body></html>\n")
