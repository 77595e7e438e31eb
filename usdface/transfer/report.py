"""What ``usdface personalize`` reports about its result: the lips in the lip shapes, generic beside output
(:func:`lip_report`), how much each mesh's shapes changed (:func:`offset_changes`, what ``--dry-run``
prints), the retarget map's rows that follow shapes the capture barely shows (:func:`untrusted_map_rows`),
and the record the layer keeps of what made it (:func:`layer_provenance`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..errors import GeometryError
from ..model import Avatar
from ..motion import shape_norms
from ..submesh import SparseOffsets

__all__ = ["LIP_SHAPES", "lip_report", "changed_vertices", "offset_changes", "untrusted_map_rows",
           "layer_provenance"]

#: Shapes whose lips the lip check looks at (``mouthClose`` posed on ``jawOpen``, as ARKit authors it).
LIP_SHAPES = ("mouthClose", "mouthPressLeft", "mouthPressRight", "mouthRollLower", "mouthRollUpper",
              "mouthPucker", "mouthFunnel", "mouthShrugLower")


def lip_report(points, triangles, names, generic, output, capture=None) -> dict:
    """Lower-lip vertices past the upper lip (:func:`usdface.personalize.contact.lip_crossings`, the lips
    found by their motion under the generic ``jawOpen``) per lip shape, generic beside output:
    ``{shape: {"generic": [count, deepest mm], "output": [count, deepest mm]}}``; ``{}`` without jawOpen.
    ``generic``/``output`` ``[J,m,3]`` in ``names`` order.

    ``capture``: ``(neutral[n,3], triangles[t,3], person[J,n,3], template[J,n,3])``, the person's fitted
    shapes and the capture's template shapes on the capture mesh (its own frame, metres; ``names`` order):
    each row then also holds ``"capture"`` and ``"template"``, the same figure on the capture mesh (the lips
    across its mouth hole), so a crossing the output carries can be told from one the person's scans show
    (on dev1 the truth's ``mouthClose`` crosses 12.9 mm deep where the generic crosses 5.1). A capture mesh
    without a mouth hole gives neither entry."""
    from ..personalize.contact import find_openings, lip_crossings, lip_pairs_from_motion, most_moved_opening

    if "jawOpen" not in names:
        return {}
    jaw = names.index("jawOpen")
    try:
        pairs = lip_pairs_from_motion(points, generic[jaw])
    except GeometryError:
        return {}
    # (label, shapes[J,m,3], the mesh's points and triangles, how lip_crossings finds its lips)
    sides = [(label, d, points, triangles, {"openings": [], "pairs": pairs})
             for label, d in (("generic", generic), ("output", output))]
    if capture is not None:
        c_points, c_triangles, c_deltas, c_template = capture
        openings = find_openings(c_points, c_triangles)
        if openings:                  # the mouth: the opening the capture's jawOpen moves most
            where = {"openings": openings, "opening": most_moved_opening(openings, c_deltas[jaw])}
            sides += [(label, d, c_points, c_triangles, where)
                      for label, d in (("capture", c_deltas), ("template", c_template))]
    out = {}
    for name in LIP_SHAPES:
        if name not in names:
            continue
        j = names.index(name)
        row = {}
        for label, d, p, t, where in sides:
            pose = d[j] + (d[jaw] if name == "mouthClose" else 0.0)
            c = lip_crossings(p, t, pose, **where)
            row[label] = [c.count, round(c.max_depth * 1e3, 3)]
        out[name] = row
    return out


def changed_vertices(result, generic, where) -> np.ndarray:
    """``[J,m]`` bool: vertices ``where[m]`` whose offset in ``result[J,m,3]`` differs from ``generic[J,m,3]``
    by more than 1e-9 m, formed shape by shape (no ``[J,m,3]`` difference)."""
    out = np.zeros(result.shape[:2], dtype=bool)
    for j in range(len(out)):
        out[j] = where & (shape_norms(result[j:j + 1] - generic[j:j + 1])[0] > 1e-9)
    return out


def offset_changes(avatar: Avatar, offsets: dict, regions: dict | None = None) -> list[dict]:
    """Per mesh and shape: largest and RMS change of the offsets (m) - what ``--dry-run`` prints. A mesh held
    on its moving part (``regions``, offsets :class:`usdface.submesh.SparseOffsets`) changes nowhere else."""
    rows = []
    for m in avatar.meshes:
        key = m.key
        new = offsets[key]
        copies = new.copies if isinstance(new, SparseOffsets) else None
        new = new.values if isinstance(new, SparseOffsets) else new
        K, held = m.deltas.shape[:2]
        n_full = regions[key].n if regions and key in regions else m.n_vertices
        # a welded part's vertex stands for itself and its copies (written with its offsets)
        count = (1 + np.bincount(copies[1], minlength=held) if copies is not None
                 else np.ones(held, dtype=np.int64))
        peak, rms, moved = np.zeros(K), np.zeros(K), np.zeros(K, dtype=np.int64)
        for k in range(K):                   # shape by shape: no [K,n] array (the twice-subdivided head's
            d = new[k] - m.deltas[k]         # 94 MB of them set the run's peak, +125 MB)
            sq = np.einsum("nc,nc->n", d, d)                             # squared change on the part held
            peak[k] = np.sqrt(sq.max()) if held else 0.0
            rms[k] = np.sqrt(sq @ count / max(n_full, 1))
            moved[k] = (sq > 1e-18) @ count
        for k, n in enumerate(m.names):
            rows.append({"mesh": key, "shape": n, "max_change_m": float(peak[k]),
                         "rms_change_m": float(rms[k]), "moved_vertices": int(moved[k])})
    return rows


def untrusted_map_rows(weights, names, k_names, trust) -> list[str]:
    """The eq. (4) map's rows ``weights[J,K]`` (capture shapes ``names``, avatar shapes ``k_names``) of shapes
    the implant barely trusts (``trust[J] < 0.5``: the capture barely shows them) whose strongest entry is
    another shape than their namesake, as ``"cheekPuff -> mouthRollLower 0.54 (cheekPuff 0.17)"``: the
    map's row is the fit's shape as it is, which the implant keeps near the generic one."""
    rows = []
    for j in np.flatnonzero(np.asarray(trust) < 0.5):
        top = int(np.argmax(weights[j]))
        if k_names[top] != names[j]:
            own = weights[j, k_names.index(names[j])] if names[j] in k_names else 0.0
            rows.append(f"{names[j]} -> {k_names[top]} {weights[j, top]:.2f} ({names[j]} {own:.2f})")
    return rows


def layer_provenance(report: dict, timings: dict, *, command: str, method: str, inputs: list,
                     extra_inputs: dict | None, registration, retarget_map, mu: float) -> dict:
    """The provenance a personalized layer records (:func:`usdface.io.layers.write_avatar_layer`): the command
    (``"usdface personalize"`` when none is given), the options the run used (``report["options"]``, other
    values as text), the method, the input files (``inputs`` and ``extra_inputs`` ``{role: path}``, each also
    under its role), the registration (``registration``: a
    :class:`usdface.transfer.register.Registration`), the correspondence's figures, the fit's test
    expressions, the eq. (4) map (``retarget_map`` rows, ``mu``), the warnings, the step timings and the
    artist pins."""
    extra = {role: str(p) for role, p in (extra_inputs or {}).items() if isinstance(p, str | Path)}
    prov = {"command": command or "usdface personalize",
            "parameters": {k: (v if isinstance(v, int | float | str | bool) else str(v))
                           for k, v in report["options"].items()},
            "method": method,
            # the face mesh the run personalized (given with --face-mesh or found): a batch row that names
            # another is not this layer's result, and the record says what to pass to reproduce it
            **({"faceMesh": str(report["face_mesh"])} if report.get("face_mesh") else {}),
            "inputs": list(inputs) + list(extra.values()),
            **extra,
            "registrationScale": float(registration.transform.scale),
            "registrationResidual": float(registration.residual),
            "registration": dict(report["registration"]),
            "correspondence": {k: v for k, v in report["correspondence"].items()
                               if isinstance(v, int | float | str)},
            **({"fitTestExpressions": report["fit"]["test_expressions"]}
               if "test_expressions" in report.get("fit", {}) else {}),
            "retargetMap": retarget_map,
            "retargetMu": float(mu), "retargetMuChoice": report["retarget"]["mu_choice"],
            "retargetGaze": report["retarget"].get("gaze", "namesake"),
            "warnings": list(report["warnings"]),
            "timings": dict(timings)}
    if (report.get("fit") or {}).get("pins"):          # the artist pins: {shape: pinned vertices}
        prov["pins"] = {str(k): int(v) for k, v in report["fit"]["pins"].items()}
    return prov
