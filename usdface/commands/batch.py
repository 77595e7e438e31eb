"""``usdface batch MANIFEST``: personalize many avatars (local process pool or Dask), isolate failures,
write a report, resume."""

from __future__ import annotations

import sys
from pathlib import Path

from .options import add_quiet, positive_int


def _option(text: str) -> tuple[str, object]:
    import argparse

    if "=" not in text:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    from ..pipeline.batch import _coerce

    key, value = text.split("=", 1)
    return key.strip(), _coerce(value)          # as a manifest cell: True/FALSE, numbers, JSON


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "batch", help="personalize many avatars from a manifest (process pool or Dask)",
        description="Personalize every (avatar, capture, output) row of a CSV/JSON manifest. Items whose "
                    "output exists are skipped (resume); a failing item is reported and the batch goes on. "
                    "Exit status 1 when any item failed.")
    p.add_argument("manifest", help="CSV with columns avatar,capture,output[,option...] or a JSON list (a "
                                    "review column true: the review page beside each layer, as a Pyblish "
                                    "publish of the manifest writes it; lines starting with # are "
                                    "comments)")
    p.add_argument("-j", "--jobs", type=positive_int, default=None,
                   help="local worker processes (default: one a CPU this process may use, no more than the "
                        "available memory holds at ~1.2 GB each; 1 = in this process)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="Dask scheduler address (tcp://host:8786): run the items on that cluster")
    p.add_argument("--force", action="store_true",
                   help="redo items whose output already exists (every row, whatever its force column; a "
                        "force column true redoes its own row)")
    p.add_argument("--report", type=Path,
                   help="where to write the JSON report (default: <manifest stem>.report.json next to the "
                        "manifest: people.csv -> people.report.json)")
    p.add_argument("--set", dest="options", action="append", type=_option, default=[], metavar="KEY=VALUE",
                   help="personalize option for every item (e.g. --set method=menzel); manifest columns win")
    p.add_argument("--worker", metavar="MODULE:FUNCTION",
                   help="run this function on each item instead of personalize (a studio's own step); it "
                        "gets the item dict and must write item['output']")
    p.add_argument("--json", action="store_true",
                   help="print the report (as written to --report) as JSON on stdout, with ok and "
                        "report_path; warnings stay on stderr")
    add_quiet(p)
    p.set_defaults(func=run)


def run(args) -> int:
    from .. import api

    def say_warnings(res) -> None:  # each item's warnings as it ends, naming it (stderr, as a command's);
        for note in res.warnings:   # they came after 'batch done', hours after the item on a long batch
            print(f"warning: {Path(res.output).name}: {note}", file=sys.stderr, flush=True)

    report = api.personalize_batch(args.manifest, jobs=args.jobs, scheduler=args.scheduler,
                                   worker=args.worker, options=dict(args.options), force=args.force,
                                   report_path=args.report, on_item=say_warnings)
    if args.json:                             # the report itself: one document on stdout
        import json

        doc = {"ok": not report.failed, "report_path": str(Path(report.report_path).absolute()),
               **report.to_dict()}
        print(json.dumps(doc, indent=1, default=str))
        return 1 if report.failed else 0
    for res in report.failed:
        print(f"FAILED {res.output}: {res.error_type}: {res.error}")
    print(report.summary())
    print(f"report: {report.report_path}")
    return 1 if report.failed else 0
