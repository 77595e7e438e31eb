"""``usdface evaluate CAPTURE``: per-method test-frame errors (Menzel et al. 2022, eq. 5), plots, error
maps."""

from __future__ import annotations

from .fit import add_fit_options, fit_kwargs
from .options import add_quiet


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "evaluate", help="compare personalization methods on the capture's test frames (eq. 5)",
        description="Fit every method on the training frames and report, per test frame, the RMSE (eq. 5) "
                    "and max vertex error in mm; optionally a plot (paper Figs. 4-5), colour-coded error "
                    "maps (Fig. 6) as a USD, a JSON report and the error against known true shapes.")
    parser.add_argument("capture", help="capture folder or capture .usda")
    parser.add_argument("--methods", default="dt,ebfr,menzel,laplacian",
                        help="comma-separated methods (default dt,ebfr,menzel,laplacian)")
    add_fit_options(parser)
    parser.add_argument("--json", metavar="JSON", help="write the full report as JSON")
    parser.add_argument("--plot", metavar="PNG", help="per-test-frame RMSE and max error bar charts")
    parser.add_argument("--usd", metavar="USDA", help="error maps as displayColor (0 mm blue, >= 5 mm red)")
    parser.add_argument("--truth", metavar="NPZ", help="capture_truth.npz: also report the error against the "
                                                       "true blendshapes")
    parser.add_argument("--force", action="store_true", help="overwrite existing outputs")
    add_quiet(parser)
    parser.set_defaults(func=run)


def run(args) -> int:
    from pathlib import Path

    from rich.console import Console
    from rich.table import Table

    from .. import api
    from ..namelist import name_list

    # the option named as typed (the API names its argument 'methods')
    methods = name_list(args.methods, "--methods", "method", fix=f"name some of {','.join(api.METHODS)}")
    truth = args.truth
    report = api.evaluate_methods(args.capture, methods, truth=truth, json_path=args.json,
                                  plot_path=args.plot, usd_path=args.usd, force=args.force,
                                  **fit_kwargs(args))
    table = Table(title=f"{Path(args.capture).name}: {len(report['labels'])} test frames (eq. 5)")
    base = report["methods"].get("dt", {}).get("mean_rmse_mm")
    # the ratio to DT only when DT ran: '--methods menzel,ebfr' printed a 'vs dt (RMSE)' column of '-' only
    ratio = ["vs dt (RMSE)"] if base else []
    for col in ("method", "mean RMSE mm", "mean max mm", *ratio):   # a method on one line: in an
        table.add_column(col, justify="right" if col != "method" else "left",   # 80-column log 'menzel
                         no_wrap=col == "method")                                 # paper' was two rows

    if truth is not None:
        table.add_column("vs truth mm", justify="right")
    table.add_column("fit s", justify="right")
    rows = list(report["methods"].items())
    if truth is not None and "template" in report:
        rows.append(("template", report["template"]))
    for name, r in rows:
        cells = [name, f"{r['mean_rmse_mm']:.3f}", f"{r['mean_max_mm']:.3f}",
                 *([f"{r['mean_rmse_mm'] / base:.2f}x"] if base else [])]
        if truth is not None:
            cells.append(f"{r['truth_rmse_mm']:.3f}" if r.get("truth_rmse_mm") is not None else "-")
        cells.append(f"{r['seconds']:.2f}" if r.get("seconds") is not None else "-")
        table.add_row(*cells)
    Console().print(table)
    for line in method_notes(report):
        print(line)
    for out in report["_outputs"].values():
        print(f"wrote {out}")
    return 0


def method_notes(report: dict) -> list[str]:
    """Lines under the table on what a method's own cross-validation chose, which its figures do not show:
    the Laplacian weight mu (``info["laplacian_weight"]``, ``info["laplacian_cv"]``). At mu = 0 the laplacian
    row is menzel's energy without the Laplacian term, and on dev3 its figures equalled menzel's to every
    printed digit after 60x the fit time, with nothing saying why."""
    lines = []
    for name, r in report["methods"].items():
        info = r.get("info") or {}
        mu = info.get("laplacian_weight")
        if mu is None:
            continue
        cv = info.get("laplacian_cv") or {}
        if cv.get("cv_rmse_mm"):
            tried = ", ".join(f"{g:g} ({e:.3f} mm)"
                              for g, e in zip(cv["grid"], cv["cv_rmse_mm"], strict=True))
            how = f"chosen by cross-validation of {tried}"
        else:
            how = cv.get("note") or "as given"
        line = f"{name}: Laplacian weight mu = {mu:g}, {how}"
        if mu == 0:
            menzel = (report["methods"].get("menzel") or {}).get("info") or {}
            amplitude = (menzel.get("steps") or {}).get("amplitude") == "applied"
            line += (": no Laplacian term, the same fit as menzel" +
                     (" before menzel's amplitude step" if amplitude else ""))
        lines.append(line)
    return lines
