"""``usdface fit CAPTURE -o rig.usda``: personalized blendshapes on the capture mesh, written as a UsdSkel
rig."""

from __future__ import annotations

from . import all_warnings, command_line, json_path, say_warning
from .options import add_quiet, positive_int, reg_value

METHOD_HELP = "dt | ebfr | menzel (default) | laplacian"
METHODS = ("dt", "ebfr", "menzel", "laplacian")  # == usdface.api.METHODS (not imported: keeps --help fast)


def add_fit_options(parser) -> None:
    """Options shared by ``fit`` and ``evaluate``."""
    parser.add_argument("--reg", default="auto", type=reg_value,
                        help="E_reg weight: 'auto' (leave-one-frame-out cross-validation, default), 'paper' "
                             "(1, the paper's plain sum, and no alignment/re-estimation: the paper's "
                             "method) or a number > 0")
    parser.add_argument("--prior", choices=("auto", "dt", "template"), default=None,
                        help="generic shapes T_j: deformation transfer (paper), raw template, or a blend "
                             "chosen by cross-validation (default with --reg auto)")
    parser.add_argument("--no-align", dest="align", action="store_false", default=None,
                        help="skip the robust rigid pre-alignment of the training frames")
    parser.add_argument("--no-reweight", dest="reweight", action="store_false", default=None,
                        help="keep the phone's training weights (no anchored re-estimation)")
    parser.add_argument("--no-amplitude", dest="amplitude", action="store_false", default=None,
                        help="menzel: keep each shape's size as its peak training frame sets it (no second "
                             "reading on the capture's test frames; eq. 5 is then wholly held out)")
    parser.add_argument("--weak-prior", dest="weak_prior", action="store_true", default=None,
                        help="menzel/laplacian: return a shape the training frames show too weakly to "
                             "measure (effective weight below 10x the phone's weight noise, 0.04) towards "
                             "its prior (off by default: it helps the phone-mesh captures and hurts "
                             "generated ones missing frames, docs/fit.md)")
    parser.add_argument("--no-eyelids", dest="eyelids", action="store_false",
                        help="no virtual eyelid triangles in the deformation transfer")
    add_contact_option(parser)


def add_contact_option(parser) -> None:
    parser.add_argument("--contact", choices=("auto", "on", "off"), default="auto",
                        help="lip and eyelid contact (menzel/laplacian): keep the vertex pairs the "
                             "template's blinks, mouthClose, mouthPress and mouthRoll bring together at the "
                             "template's gap; auto (default) only where the training frames agree (a "
                             "likelihood-ratio test), on for every such shape, off to only measure the gaps")


def add_pins_option(parser) -> None:
    parser.add_argument("--pins", metavar="FILE",
                        help="artist pins (menzel/laplacian): keep these vertices of these shapes at the "
                             "template's version; a JSON file {\"pins\": {\"jawOpen\": [12, 13]}} or a USD "
                             "file with per-vertex primvars usdface:pin:<shape> (e.g. the painted capture)")


def add_every_option(parser) -> None:
    parser.add_argument("--every", type=positive_int, default=1, metavar="N",
                        help="a take given as the capture: fit every N-th frame (default 1: all; a long "
                             "take's fit costs time and memory in proportion to its frames, docs/takes.md)")


def fit_kwargs(args) -> dict:
    return {"reg": args.reg, "prior": args.prior, "align": args.align, "reweight": args.reweight,
            "eyelids": args.eyelids, "contact": args.contact,
            **({"amplitude": args.amplitude} if getattr(args, "amplitude", None) is not None else {}),
            **({"weak_prior": args.weak_prior} if getattr(args, "weak_prior", None) is not None else {}),
            **({"every": args.every} if getattr(args, "every", 1) != 1 else {})}


def take_line(info: dict) -> str | None:
    """One line on a weighted (whole-take) fit: frames, effective frames (Kish), the weighting."""
    fw = info.get("frame_weights")
    if not fw:
        return None
    every = f" (every {_ordinal(info['whole_take_every'])} frame)" if info.get("whole_take_every") else ""
    poses = f", {info['take_poses']:.0f} distinct poses" if info.get("take_poses") is not None else ""
    if fw["mode"].startswith("equally"):
        return f"whole take: {fw['frames']} frames{every}{poses} weighted {fw['mode']}"
    return (f"whole take: {fw['frames']} frames{every}{poses} weighted {fw['mode']} (as many as "
            f"{fw['effective_frames']:.0f} equally weighted frames; weights {fw['min']:.3g}-{fw['max']:.3g})")


def weak_line(weak: dict | None) -> str | None:
    """One line on the shapes the frames show too weakly to measure: each one's factor towards its prior."""
    if not weak:
        return None
    shown = ", ".join(f"{name} {factor:.2f}" for name, factor in weak.items())
    return f"shown too weakly to measure, kept towards the prior (0: the prior, 1: as fitted): {shown}"


#: How the summary names each optional step of the fit (``info["steps"]``,
#: :func:`usdface.personalize.api.fit_steps`).
STEP_NAMES = {"align": "alignment", "reweight": "weight re-estimation", "contact": "contact",
              "amplitude": "amplitude", "weak_prior": "weak prior"}


def steps_line(steps: dict | None) -> str | None:
    """One line on what each optional step of the fit did (``--no-amplitude`` and the default printed the
    same summary): ``steps: alignment applied, weight re-estimation not applied (...), ...``."""
    if not steps:
        return None
    return "steps: " + ", ".join(f"{STEP_NAMES.get(k, k)} {v}" for k, v in steps.items())


def contact_lines(contact: dict | None) -> list[str]:
    """One line per contact shape: pairs, the largest gap vs the template's before -> after (mm)."""
    if not contact or not contact.get("shapes"):
        return []
    lines = [f"contact ({contact['mode']}): largest gap vs the template's, mm (before -> after)"]
    for name, r in contact["shapes"].items():
        how = "corrected" if r["applied"] else ("frames disagree" if "test" in r else "not corrected")
        lines.append(f"  {name}: {r['pairs']} pair(s), {r['gap_before_mm']:.3f} -> {r['gap_after_mm']:.3f} "
                     f"({how})")
    return lines


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "fit", help="personalized ARKit blendshapes on the capture mesh (the 'face mask' rig)",
        description="Fit the person's blendshapes from a capture (Menzel et al. 2022, eqs. 1-3, or a "
                    "baseline) and write them as a UsdSkel rig on the capture mesh, in its vertex order.")
    parser.add_argument("capture", help="capture folder or capture .usda, or a take (USD take or "
                                        "OBJ-sequence folder with a Live Link CSV): every frame fitted "
                                        "(docs/takes.md)")
    parser.add_argument("-o", "--output", required=True, help="output rig .usda/.usdc")
    parser.add_argument("--method", default="menzel", choices=METHODS,
                        help=METHOD_HELP)
    add_fit_options(parser)
    add_pins_option(parser)
    add_every_option(parser)
    parser.add_argument("--force", action="store_true", help="overwrite an existing output")
    parser.add_argument("--json", action="store_true", help="print the fit's summary as JSON")
    add_quiet(parser)
    parser.set_defaults(func=run)


def run(args) -> int:
    from .. import api

    pins = {"pins": args.pins} if args.pins else {}
    result = api.fit_capture(args.capture, method=args.method, out_path=args.output, force=args.force,
                             command=command_line(), **fit_kwargs(args), **pins)
    info = result.info
    if args.json:
        import json

        from ..io.layers import json_default

        doc = {"ok": True, "output": json_path(info["out_path"]), "method": args.method,
               "shapes": list(result.rig.names), "vertices": int(result.rig.n_vertices),
               **{k: v for k, v in info.items() if k in ("reg", "prior_alpha", "train_rmse_mm", "timings",
                                                         "warnings", "contact", "frame_weights",
                                                         "take_poses", "weak", "steps")}}
        doc["warnings"] = all_warnings(info.get("warnings"))
        print(json.dumps(doc, default=json_default))
        return 0
    rmse = f"; train RMSE {info['train_rmse_mm']:.3f} mm" if info.get("train_rmse_mm") is not None else ""
    extra = f", reg {info['reg']:.3g}" if "reg" in info else ""
    if "prior_alpha" in info and args.method in ("menzel", "laplacian"):
        extra += f", prior {info['prior_alpha']:.2f} DT + {1 - info['prior_alpha']:.2f} template"
    print(f"wrote {info['out_path']}: {len(result.rig.names)} shapes on {result.rig.n_vertices} vertices "
          f"({args.method}{extra}{rmse}; "
          f"{info['timings']['total']:.2f} s)")
    for line in [steps_line(info.get("steps")), take_line(info), weak_line(info.get("weak")),
                 *contact_lines(info.get("contact"))]:
        if line:
            print(line)
    for w in info["warnings"]:
        say_warning(w)
    return 0


def _ordinal(n: int) -> str:
    """2nd, 3rd, 4th, 11th, 21st ..."""
    n = int(n)
    suffix = "th" if 10 <= n % 100 <= 20 else {1: "st", 2: "nd", 3: "rd"}.get(n % 10, "th")
    return f"{n}{suffix}"
