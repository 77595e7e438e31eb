"""Method comparison for ``usdface evaluate``: fit every method, score it on the test frames (eq. 5), build
the per-frame table, the error maps (Fig. 6 colours) and the bar plot (Figs. 4-5). No USD here."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from ..errors import FitError
from ..model import Capture
from ..progress import steps
from .api import FIT_FLAGS, METHODS, fit_personalized_shapes, left_out_scale
from .evaluate import error_colors, evaluate_rig, truth_error

__all__ = ["check_method_options", "evaluate_methods", "plot_errors", "write_report_json"]


#: The runs a method stands for in the comparison: ``(report key, method, options)``. Each method is shown
#: as its authors tuned it and as this package tunes it, so that tuned meets tuned: ``menzel`` (default:
#: CV of the balance and prior, CV-gated alignment and re-estimation) beside ``menzel paper`` (reg = 1,
#: the method as published); ``ebfr`` (Li et al.'s beta = 0.5) beside ``ebfr tuned`` (beta by the same
#: leave-one-frame-out CV as menzel, the same CV-gated alignment).
VARIANTS = {"dt": (("dt", "dt", {}),),
            "menzel": (("menzel", "menzel", {}), ("menzel paper", "menzel", {"reg": "paper"})),
            "ebfr": (("ebfr", "ebfr", {"beta": 0.5}), ("ebfr tuned", "ebfr", {"beta": "auto"})),
            "laplacian": (("laplacian", "laplacian", {}),)}

#: The user options each method takes (the rest would be refused as unused).
_TAKES = {"dt": ("eyelids",), "ebfr": ("eyelids", "align"),
          "menzel": ("reg", "prior", "align", "reweight", "eyelids", "contact", "amplitude", "weak_prior"),
          "laplacian": ("reg", "prior", "align", "reweight", "eyelids", "contact", "weak_prior")}


#: The command line's spelling of each fit option, for the refusal of one no chosen method uses.
_FLAGS = {k: FIT_FLAGS[k] for k in ("reg", "prior", "align", "reweight", "contact", "eyelids", "amplitude",
                                    "weak_prior")}


def check_method_options(methods, fit_options: dict) -> None:
    """Refuse (FitError, before any fitting) an unknown method, no method, and a fit option that none of
    ``methods`` takes (``--methods dt --reg 0.5``: the number was ignored and the table looked like its
    answer). ``None`` and the defaults (``reg``/``contact`` "auto") count as not given."""
    bad = [m for m in methods if m not in METHODS]
    if bad or not methods:
        raise FitError(f"unknown method(s) in --methods: {', '.join(bad) or '(none)'}",
                       fix=f"use a comma-separated subset of {','.join(METHODS)}")   # an option, not the file
    # an option evaluate passes to no fit (a typo, 'regg'; a fit option it does not pass, 'pins'): dropped
    # without a word, the table looked like its answer (evaluate_methods(c, "menzel", regg=5) ran at reg auto)
    unknown = [k for k in fit_options if k not in _FLAGS]
    if unknown:
        raise FitError(f"option(s) evaluate does not take: {', '.join(unknown)} (they would be ignored)",
                       fix=f"drop them; evaluate passes {', '.join(_FLAGS)} to the methods that take them "
                           "(for the fit's other options fit one method with fit_capture / usdface fit)")
    given = [k for k, v in fit_options.items()
             if k in _FLAGS and v is not None and not (k in ("reg", "contact") and v == "auto")]
    unused = [k for k in given if not any(k in _TAKES[m] for m in methods)]
    if unused:
        users = [m for m in METHODS if all(k in _TAKES[m] for k in unused)]
        named = ", ".join(f"{_FLAGS[k]} ({k}={fit_options[k]!r})" for k in unused)
        raise FitError(f"{named} not used by --methods {','.join(methods)} (it would be ignored)",
                       fix=f"drop it, or add {' or '.join(users) or 'a method that uses it'} to --methods")


def evaluate_methods(capture: Capture, methods, *, truth: dict | None = None, variants: bool = True,
                     **fit_options) -> dict:
    """Fit and score ``methods`` on ``capture``.

    With ``variants`` each method stands for its runs in :data:`VARIANTS` (menzel also at the paper's
    balance, EBFR also tuned); ``fit_options`` go to the methods that take them (``reg``/``prior``/
    ``reweight`` only to menzel and laplacian, ``align`` not to dt), a variant's own options win.

    ``truth`` (optional): ``{"names": [K], "deltas": [K,n,3]}`` (bench ``capture_truth.npz``); adds
    ``truth_rmse_mm`` per method and a ``template`` row (the generic template deltas' error).
    Returns ``{"labels": [F], "methods": {name: {"rmse_mm": [F], "max_mm": [F], "mean_rmse_mm",
    "mean_max_mm", "truth_rmse_mm", "seconds", "info"}}, "_maps": {...}}`` (``_maps`` feeds the USD writer).
    """
    check_method_options(methods, fit_options)
    test = capture.test
    order = None
    if truth is not None:
        tnames = [str(n) for n in np.asarray(truth["names"]).tolist()]
        missing = [n for n in capture.names if n not in tnames]
        if missing:
            raise FitError(f"truth lacks shape(s) {', '.join(missing[:5])}",
                           fix="pass the capture's own truth")
        order = [tnames.index(n) for n in capture.names]
        true_deltas = np.asarray(truth["deltas"])[order]
        if true_deltas.shape[1:] != (len(capture.neutral), 3):
            raise FitError(f"truth deltas are for {true_deltas.shape[1]} vertices, the capture has "
                           f"{len(capture.neutral)}", path=capture.source or None,
                           fix="pass the capture's own capture_truth.npz")
    report: dict = {"labels": list(test.label), "methods": {}, "_maps": {}}
    runs = [run for m in methods for run in (VARIANTS[m] if variants else ((m, m, {}),))]
    with steps("methods", len(runs)) as p:
        for key, m, own in runs:
            p.start(f"fit and score {key}")
            opts = {k: v for k, v in fit_options.items() if k in _TAKES[m] and v is not None}
            if own.get("reg") == "paper":
                opts = {k: v for k, v in opts.items() if k == "eyelids"}
            opts.update(own)
            t0 = time.perf_counter()
            res = fit_personalized_shapes(capture, method=m, **opts)
            sec = time.perf_counter() - t0
            ev = evaluate_rig(res.rig, test, left_out_scale(res, test))      # cross-fitted (amplitude)
            row = {"rmse_mm": ev["rmse_mm"].tolist(), "max_mm": ev["max_mm"].tolist(),
                   "mean_rmse_mm": ev["mean_rmse_mm"], "mean_max_mm": ev["mean_max_mm"], "seconds": sec,
                   "truth_rmse_mm": None if order is None else truth_error(res.rig.deltas, true_deltas),
                   "info": report_info(res.info)}
            report["methods"][key] = row
            report["_maps"][key] = [(lab, pts, err, error_colors(err)) for lab, pts, err
                                    in zip(test.label, test.points, ev["vertex_mm"], strict=True)]
    if order is not None:
        from ..model import FaceRig
        tr = FaceRig(capture.neutral, capture.triangles, capture.names, capture.template.deltas)
        ev = evaluate_rig(tr, test)
        report["template"] = {"rmse_mm": ev["rmse_mm"].tolist(), "max_mm": ev["max_mm"].tolist(),
                              "mean_rmse_mm": ev["mean_rmse_mm"], "mean_max_mm": ev["mean_max_mm"],
                              "truth_rmse_mm": truth_error(capture.template.deltas, true_deltas),
                              "seconds": None}
    return report


#: Per-frame and per-vertex arrays of a fit's ``info`` that a report leaves out (the rig holds the shapes).
_BULK_INFO = ("train_weights", "test_scale_left_out", "prior_deltas", "weight_sensitivity", "weight_leak",
              "weight_leak_direction", "weight_leak_along", "frame_variance")


def report_info(info: dict) -> dict:
    """A fit's ``info`` as the report keeps it: its summaries, without :data:`_BULK_INFO` (eq. 2's prior
    shapes, ``[K,n,3]``, made ``--json`` 12 MB on a 1,200-vertex capture, 3/4 of it that array) nor any
    other per-vertex array (ndim >= 3)."""
    return {k: v for k, v in info.items()
            if k not in _BULK_INFO and not (isinstance(v, np.ndarray) and v.ndim >= 3)}


def write_report_json(report: dict, path, force: bool = False) -> Path:
    """Write the report (without the error maps) as JSON; atomic (temp + rename)."""
    from ..io.atomic import write_text_atomic
    from ..io.layers import json_default

    data = {k: v for k, v in report.items() if not k.startswith("_")}
    return write_text_atomic(path, json.dumps(data, indent=1, default=json_default), force=force)


#: The widest a plot's row of test frames gets, inches (at 120 dpi: 4,800 px); more frames wrap onto further
#: rows (a take's 222 test frames made one 23,000-pixel-wide picture).
PLOT_MAX_WIDTH_IN = 40.0


def plot_errors(report: dict, path, force: bool = False, title: str | None = None) -> Path:
    """Bar charts like Menzel et al. (2022), Figs. 4-5: per test expression, RMSE (top) and max error
    (bottom), methods side by side; frames beyond :data:`PLOT_MAX_WIDTH_IN` of a row wrap onto further
    RMSE / max-error pairs; ``title`` above them (what was evaluated: the picture alone did not say which
    capture it scores). Atomic write (temp + rename)."""
    # a Figure of its own, not pyplot + matplotlib.use("Agg"): they switched the host's backend and closed
    # its figures (a notebook's, a DCC's)
    from matplotlib.figure import Figure

    from ..io.atomic import atomic_file

    labels = [str(lab) for lab in report["labels"]]
    methods = list(report["methods"])
    width = 0.8 / max(len(methods), 1)
    per_frame = 0.35 * max(len(methods), 1) / 2                  # inches of one frame's group of bars
    per_row = max(1, int(PLOT_MAX_WIDTH_IN // per_frame))
    chunks = [range(s, min(s + per_row, len(labels))) for s in range(0, len(labels), per_row)] or [range(0)]
    fig = Figure(figsize=(max(8.0, per_frame * len(chunks[0])), 7 * len(chunks)))
    axes = fig.subplots(2 * len(chunks), 1, squeeze=False)[:, 0]
    panels = (("rmse_mm", "RMSE (eq. 5)"), ("max_mm", "maximum vertex error"))
    # the frames' own labels, as the JSON report and the error maps' prims name them (it numbered them from
    # 1: the JSON's '003' was the plot's 4)
    long = max((len(lab) for lab in labels), default=0) > 4
    for c, frames in enumerate(chunks):
        x = np.arange(len(frames))
        pair = axes[2 * c:2 * c + 2]
        for ax, (key, panel) in zip(pair, panels, strict=True):
            for k, m in enumerate(methods):
                values = np.asarray(report["methods"][m][key], dtype=float)[list(frames)]
                ax.bar(x + (k - (len(methods) - 1) / 2) * width, values, width, label=m)
            ax.set_ylabel("mm")
            ax.set_title(panel if len(chunks) == 1 else
                         f"{panel}, test expressions {labels[frames[0]]}-{labels[frames[-1]]}"
                         if len(frames) else panel)
            ax.grid(axis="y", alpha=0.3)
            ax.set_xlim(-0.5, per_row - 0.5 if len(chunks) > 1 else max(len(frames), 1) - 0.5)
        pair[0].set_xticks(x, [])
        pair[1].set_xticks(x, [labels[i] for i in frames], rotation=90 if long else 0,
                           fontsize="small" if long else None)
        pair[1].set_xlabel("test expression")
    if len(chunks) > 1:                                  # one scale per quantity over the wrapped rows
        for key, row_axes in (("rmse_mm", axes[0::2]), ("max_mm", axes[1::2])):
            top = max((float(np.nanmax(report["methods"][m][key])) for m in methods
                       if len(report["methods"][m][key])), default=0.0)
            for ax in row_axes:
                ax.set_ylim(0.0, 1.05 * top or 1.0)
    axes[0].legend(ncol=len(methods))
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    with atomic_file(path, force=force) as tmp:
        fig.savefig(tmp, dpi=120)
    return Path(path)
