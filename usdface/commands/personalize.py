"""``usdface personalize AVATAR CAPTURE -o OUT``: implant the person's shapes into the avatar (USD layer)."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from . import add_name_map_option, all_warnings, command_line, json_path, say_warning
from .fit import add_contact_option, add_every_option, add_pins_option, take_line
from .options import mu_value, nonnegative_float, positive_float, reg_value, weight_bound

#: A .usda layer larger than this gets a note that .usdc holds it in about a third of the bytes and reads
#: faster (bytes; the 225k-vertex head's layer was 358 MB of text, 100 MB as .usdc, read 2.2x faster).
TEXT_LAYER_NOTE_BYTES = 50_000_000


def add_transfer_options(p) -> None:
    """Options shared by ``personalize`` and ``retarget``: the inputs, the fit and eq. (4)'s map (the
    implant's own are :func:`add_implant_options`, ``personalize`` only)."""
    p.add_argument("avatar", help="UsdSkel avatar (.usd/.usda/.usdc) with ARKit-named BlendShapes")
    p.add_argument("capture", help="capture folder (neutral.obj, template/, train/) or capture .usda, or a "
                                   "take (USD take or OBJ-sequence folder with a Live Link CSV): every frame "
                                   "fitted, a held pose counted once (docs/takes.md)")
    p.add_argument("--method", default="menzel", choices=["menzel", "dt", "ebfr", "laplacian"],
                   help="capture fit method (default: menzel, the paper's eqs. 1-3)")
    p.add_argument("--reg", default="auto", type=reg_value,
                   help="fit regularisation: auto (cross-validated), paper, or a number > 0")
    p.add_argument("--mu", type=mu_value, default="auto",
                   help="eq. (4) ridge weight relative to the shapes' mean squared norm, or auto "
                        "(cross-validated by leaving out one region of the face at a time; default)")
    bounds = p.add_mutually_exclusive_group()      # --unbounded would drop the bounds given without a word
    bounds.add_argument("--weight-bounds", nargs=2, type=weight_bound, default=(0.0, 1.0),
                        metavar=("LO", "HI"),
                        help="range of the eq. (4) map's weights (default 0 1: the range an ARKit rig's "
                             "channels are authored for, so an engine can drive the avatar with the map as "
                             "it is)")
    bounds.add_argument("--unbounded", action="store_true",
                        help="eq. (4) as the paper: any real weights (not with --weight-bounds)")
    p.add_argument("--map-prior", default="namesake", choices=["namesake", "zero"],
                   help="what eq. (4)'s ridge shrinks each row of the map towards: the avatar shape of the "
                        "same ARKit name (default, as a hand-made retargeting table) or zero (the paper)")
    p.add_argument("--map-gaze", default="namesake", choices=["namesake", "free"],
                   help="the map's gaze channels (eyeLook*, which an engine turns the eyes with): driven by "
                        "their namesake capture shape alone (default: no blink turns the eyes) or free "
                        "(eq. 4 as it is: any shape may drive them)")
    p.add_argument("--prior", default="avatar", choices=["avatar", "template"],
                   help="what the fit shrinks towards where the capture does not inform a shape: the "
                        "avatar's own generic shapes on the capture mesh (default) or the capture's template")
    p.add_argument("--correspondence", metavar="FILE",
                   help="correspondence cache (.npz): reused when it matches the avatar face and the "
                        "capture's template, written otherwise (a cache of another avatar is rewritten, "
                        "with a warning: it is a cache, not an input)")
    add_contact_option(p)
    add_every_option(p)
    add_name_map_option(p)
    p.add_argument("--quiet", "-q", action="store_true", help="no progress bars")


def add_implant_options(p) -> None:
    """The implant's options (how the face region receives the shapes, what lies beyond, the eyelid repair):
    ``personalize`` only; ``retarget`` writes eq. (4)'s map and uses none of them."""
    p.add_argument("--face-transfer", default="person", choices=["person", "offset", "dt", "dt-offset"],
                   help="how the face region receives the shapes (default: person = the person's motion "
                        "A_j + M(B_j - P_j); offset = the older B_j - T_j deviation; dt = the paper's DT)")
    p.add_argument("--approximation", default=None, choices=["field", "generic", "retarget"],
                   help="what lies beyond the face and the other meshes follow: field (default with "
                        "--face-transfer person: the person's rotation+scale field of the generic motion, "
                        "extended smoothly), generic (default with the older modes) or retarget (eq. 4, the "
                        "paper)")
    # None: not given (a mode that does not use an option refuses it when given, MODE_OPTIONS)
    p.add_argument("--extension-length", type=positive_float, default=None,
                   help="--face-transfer person only: how far the person's motion reaches beyond the face "
                        "before it fades to the generic, in face radii (default 1)")
    p.add_argument("--falloff", type=nonnegative_float, default=None,
                   help="older modes only (offset, dt, dt-offset): width of the seamless join beyond the "
                        "face in capture edge lengths (default 0.15; 0 = harmonic over the whole adjacent "
                        "region, as in the paper)")
    p.add_argument("--no-eyelids", action="store_true", help="skip the eyelid-eyeball repair")


def transfer_kwargs(args) -> dict:
    """The keyword arguments of :func:`add_transfer_options` for :func:`usdface.api.personalize_avatar` /
    :func:`usdface.api.write_retarget_map`."""
    reg = args.reg
    try:
        reg = float(reg)
    except ValueError:
        pass
    return {"method": args.method, "reg": reg, "mu": args.mu, "correspondence": args.correspondence,
            "prior": args.prior, "name_map": args.name_map, "contact": args.contact,
            **({"every": args.every} if getattr(args, "every", 1) != 1 else {}),
            "weight_bounds": None if args.unbounded else tuple(args.weight_bounds),
            "map_prior": args.map_prior, "map_gaze": args.map_gaze}


def implant_kwargs(args) -> dict:
    """The keyword arguments of :func:`add_implant_options`: an option left out stays out (the mode's
    default applies; one the mode does not use is refused only when given)."""
    given = {"approximation": args.approximation, "extension_length": args.extension_length,
             "falloff": args.falloff}
    return {"face_transfer": args.face_transfer, "eyelids": not args.no_eyelids,
            **{k: v for k, v in given.items() if v is not None}}


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "personalize", help="implant personalized ARKit shapes from a capture into an avatar (USD layer)",
        description="Fit the person's ARKit blendshapes on the capture, register and correspond the capture "
                    "with the avatar's face, and write a new USD layer over the untouched avatar with "
                    "personalized offsets for every BlendShape (Menzel et al. 2022, sec. 3.2-3.3).")
    add_transfer_options(p)
    add_implant_options(p)
    add_pins_option(p)
    p.add_argument("-o", "--output", help="output layer (.usda/.usdc; default: "
                                          "<avatar name>.personalized.usda in the current folder)")
    p.add_argument("--force", action="store_true", help="overwrite the output")
    p.add_argument("--face-mesh", metavar="PRIM",
                   help="prim name or path of the face mesh (default: the mesh the capture's shapes "
                        "move most)")
    p.add_argument("--dry-run", action="store_true",
                   help="compute and print what would change; write no layer (a --correspondence cache "
                        "is still written: the next run reuses it) (exit status 1 when a real run would "
                        "refuse to write: an existing output without --force, an instanced avatar)")
    p.add_argument("--json", action="store_true", help="print the report as JSON")
    p.add_argument("--inspect", action="store_true",
                   help="also write inspection data for usdview into the layer: a displayColor heat map of "
                        "how much each vertex changed and a SkelAnimation playing the capture's test "
                        "expressions on the personalized avatar")
    p.add_argument("--landmarks", action="store_true",
                   help="with the inspection data, the personalized face's landmark layout as Points "
                        "(about 1.5 s more on a 14k-vertex head; implies --inspect)")
    p.add_argument("--take", metavar="FILE",
                   help="append this take to the inspection animation: a Live Link Face CSV, a USD take or "
                        "an OBJ-sequence take folder (implies --inspect)")
    p.add_argument("--review", action="store_true",
                   help="also write the review page (usdface review) beside the layer: <layer>.review.html")
    p.set_defaults(func=run)


def _default_output(avatar: str) -> Path:
    """``<avatar stem>.personalized.usda`` in the current folder (the avatar's folder is often a read-only
    asset library)."""
    from ..api import personalized_name

    return Path(personalized_name(avatar))


def _refuse_layer_over(avatar) -> None:
    """:func:`usdface.io.usd_rig.refuse_layer_over` of the ``avatar`` path (its :class:`RigError` raised),
    for a dry run's checks before the work; any other problem of the file (not a USD file, ...) is left to
    the API, which names it in its own order."""
    from ..errors import RigError, UsdFaceError
    from ..io.usd_rig import refuse_layer_over

    try:
        refuse_layer_over(avatar)
    except RigError:
        raise
    except UsdFaceError:
        pass


def run(args) -> int:
    from .. import progress
    from ..api import personalize_avatar, personalize_inputs, refuse_missing_inputs
    from ..errors import UsdFaceError
    from ..io.atomic import check_output_file, outputs_all_or_nothing
    from ..io.layers import check_output_path
    from .review import default_output

    if args.quiet or args.json:
        progress.set_enabled(False)
    out = Path(args.output) if args.output else _default_output(args.avatar)
    inspect = bool(args.inspect or args.landmarks or args.take)
    inputs = personalize_inputs(args.avatar, args.capture, take=args.take, pins=args.pins,
                                name_map=args.name_map)
    refusal = None
    if args.review or args.dry_run:
        # a missing input before the page's problems or the dry run's early word on the output (the API
        # says it before the layer's): a dry run of a missing capture into a read-only folder printed the
        # output's refusal first
        refuse_missing_inputs(args.avatar, args.capture, args.take)
    if args.dry_run:  # nothing is written, but say whether a real run would be allowed to write
        try:
            check_output_path(args.output or out, args.force, inputs=inputs,   # as given: newdir/ a folder
                              example=_default_output(args.avatar).name)
            if args.review:
                check_output_file(default_output(out), args.force, suffixes=(".html",), what="review page",
                                  inputs=inputs)
            # an avatar under an instance (or shapes a layer cannot override): a real run refuses it once
            # it has read the avatar, before the fit; a dry run said it only after the fit (stop 52)
            _refuse_layer_over(args.avatar)
        except UsdFaceError as exc:
            from ..cli import name_output_option

            name_output_option(exc, args)        # the real run's wording: -o where -o gives the output
            refusal = str(exc)
            # said before the fit (seconds to minutes), not only after it: a preflight's answer first; the
            # changes are still computed (a dry run prints them), the exit status stays 1
            print(f"usdface personalize: dry run: a real run would refuse to write: {refusal}; computing "
                  "what would change anyway", file=sys.stderr, flush=True)
    elif args.review:  # refuse an existing review page (or an input) before the work, like the layer
        check_output_file(default_output(out), args.force, suffixes=(".html",), what="review page",
                          inputs=inputs)
    page = None
    done = {}
    # the layer and its review page all or nothing, as export's outputs (and the Pyblish publish's): a page
    # that failed (a full disk, Ctrl-C, a take it cannot play) left the new layer behind under exit status
    # 130 or 2, and the rerun refused it ('output layer exists')
    review = default_output(out) if args.review and not args.dry_run else None
    with outputs_all_or_nothing(done, layer=out if review else None, review=review):
        result = personalize_avatar(args.avatar, args.capture, args.output or out, force=args.force,
                                    dry_run=args.dry_run,
                                    command=command_line(), inspect=inspect,
                                    landmarks=args.landmarks, take=args.take, face_mesh=args.face_mesh,
                                    **transfer_kwargs(args), **implant_kwargs(args),
                                    **({"pins": args.pins} if args.pins else {}))
        if review and result.out_path:
            # written before either report: --json returned before it, and the page was never written
            from ..api import write_review

            done["layer"] = Path(result.out_path)
            page = write_review(result.out_path, default_output(result.out_path), capture=args.capture,
                                take=args.take, force=args.force)
            done["review"] = page
    rep = result.report
    # a dry run says whether a real run would write: exit status 1 when it would refuse (a preflight)
    refusal = refusal or rep.pop("would_refuse", None)
    if args.json:
        # ok: a real run would do what is asked (a dry run a real run would refuse: false, exit 1)
        doc = {"ok": not (args.dry_run and refusal), "output": json_path(result.out_path)}
        doc.update((k, v) for k, v in rep.items() if k not in ("name_report", "ok", "output"))
        if args.review:
            doc["review"] = json_path(page)
        doc["warnings"] = all_warnings(rep.get("warnings"))
        if args.dry_run:
            doc["would_write"] = None if refusal else str(out)
            if args.review:    # 'review': null alone said nothing of the page a real run would write
                doc["would_write_review"] = None if refusal else str(default_output(out))
            doc["output_refused"] = refusal
        json.dump(doc, sys.stdout, indent=1, default=str)
        print()
        return 1 if args.dry_run and refusal else 0
    import numpy as np

    reg = rep["registration"]
    angle = np.degrees(np.arccos(np.clip((np.trace(np.asarray(reg["rotation"])) - 1.0) / 2.0, -1.0, 1.0)))
    move = ", ".join(f"{v * 100:.1f}" for v in reg["translation_m"])
    print(f"registration: scale {reg['scale']:.4f}, rotation {angle:.1f} deg, translation ({move}) cm, "
          f"residual {reg['residual_m'] * 1000:.2f} mm, fitness {reg['fitness']:.2f} ({reg['initialiser']})")
    cor = rep["correspondence"]
    source = {"person": ", from the person's scan", "template": ", from the template's neutral"}.get(
        cor.get("source"), "")
    print(f"correspondence: {rep['face_vertices']} face vertices on {rep['face_mesh']}{source} (cache: "
          f"{cor.get('cache', 'off')}); {len(rep['shapes'])} shapes implanted")
    if cor.get("cache") == "replaced":
        say_warning(f"--correspondence {args.correspondence} held the map of another avatar face, template "
                    "or person's neutral scan (or an older usdface): it was rewritten for this one; give "
                    "each avatar and capture its own file to keep both")
    whole_take = rep.get("whole_take")
    fit_line = take_line(rep.get("fit") or {})
    if fit_line:
        print(f"fit: {fit_line}")
    noise = (rep.get("fit") or {}).get("weight_noise")
    if noise is not None:
        print(f"fit: the phone's weights are off by ~{noise:.2g} as the frames show it; each shape is "
              "trusted above what that leaks into it and what re-estimating the weights changes")
    eyes = rep.get("eyelids")
    if eyes and eyes["eyeballs"]:
        print(f"eyelids: {eyes['repaired_vertex_shapes']} vertex-shape pairs moved back onto the eyeballs "
              f"({', '.join(eyes['eyeballs'])})")
    lips = rep.get("lips") or {}
    if lips:
        deeper = [f"{k} {v['output'][1]:.1f} mm (generic {v['generic'][1]:.1f}"
                  + (f"; on the capture mesh the person's {v['capture'][1]:.1f}, its template's "
                     f"{v['template'][1]:.1f}" if "capture" in v else "") + ")"
                  for k, v in lips.items() if v["output"][1] > v["generic"][1] + 0.5]
        print("lips: " + ("lower lip deeper past the upper lip than generic: " + ", ".join(deeper) if deeper
                          else "lower lip past the upper lip no deeper than in the generic shapes (+0.5 mm)"))
    if rep.get("within_noise"):
        print("trust: kept near the avatar's generic shape, the capture's difference no larger than its "
              "noise: " + ", ".join(rep["within_noise"]))
    for w in rep["warnings"]:
        say_warning(w)
    # a shape whose every vertex moved by at most 1 nm (float noise of the solve) is left generic, as the
    # review page says: counted "personalized" it made the CLI's count disagree with the page's
    changed = [c for c in rep["changes"] if c["moved_vertices"] > 0]
    count = f"{len(changed)} of {len(rep['changes'])} BlendShapes"
    by_mesh = _changed_by_mesh(rep["changes"], changed)
    if args.dry_run:
        print(f"dry run: {count} would change{by_mesh} (largest change per shape, mm):")
        for c in changed:
            print(f"  {c['mesh']}/{c['shape']}: max {c['max_change_m'] * 1000:.3f}, "
                  f"rms {c['rms_change_m'] * 1000:.3f}, {c['moved_vertices']} vertices")
        print(f"a real run would refuse to write: {refusal}" if refusal else f"would write {out}"
              + (f" and its review page {default_output(out)}" if args.review else ""))
    else:
        print(f"{count} personalized{by_mesh} -> {result.out_path}")
        _text_layer_note(result.out_path)
        if inspect:
            extra = " + landmark Points" if args.landmarks else ""
            if whole_take:  # the capture is a take read whole: no test expressions
                anim = f"SkelAnimation of the take {args.take}" if args.take else \
                    f"SkelAnimation of the take {args.capture}"
            elif args.take and not (result.report.get("inspection") or {}).get("test_frames", 1):
                # a capture without test frames ('capture select' that held out none): the take alone
                anim = f"SkelAnimation of the take {args.take} (the capture has no test expressions)"
            else:
                anim = "test-expression SkelAnimation" + (f" + take {args.take}" if args.take else "")
            if not (result.report.get("inspection") or {}).get("animation_frames", 1):
                anim = ("no SkelAnimation (the capture has no test expressions; --take TAKE plays a "
                        "recording)")
            print(f"inspection: change heat map (displayColor), {anim}{extra}")
    if page is not None:
        print(f"review page: {page} ({page.stat().st_size / 1e6:.1f} MB)")
    t = rep["timings"]
    print("time: " + ", ".join(f"{k} {v:.2f}s" for k, v in t.items()))
    return 1 if args.dry_run and refusal else 0


def _changed_by_mesh(changes: list[dict], changed: list[dict]) -> str:
    """`` (/Avatar/Head 44 of 51, /Avatar/Mouth 3 of 50)`` where the BlendShapes are on more than one mesh:
    dev1 said "47 BlendShapes personalized" after "51 shapes implanted", read as 4 of the capture's shapes
    left out where 44 of the head's 51 and 3 of the mouth's 50 changed (a user trial, stop 50)."""
    from collections import Counter

    total = Counter(c["mesh"] for c in changes)
    if len(total) < 2:
        return ""
    done = Counter(c["mesh"] for c in changed)
    return " (" + ", ".join(f"{mesh} {done[mesh]} of {n}" for mesh, n in total.items()) + ")"


def _text_layer_note(path) -> None:
    """A note when the layer written is a large ``.usda``: text is ~3.6x the bytes of ``.usdc`` for offsets
    and ~2x slower to read back (``review``, ``render``, ``export`` and every DCC read it)."""
    path = Path(path)
    if path.suffix.lower() != ".usda" or not path.is_file():
        return
    size = path.stat().st_size
    if size > TEXT_LAYER_NOTE_BYTES:
        print(f"note: {path.name} is {size / 1e6:,.0f} MB of text (.usda); as .usdc (binary, -o "
              f"{path.with_suffix('.usdc').name}) the same layer is about a third of that and reads about "
              "twice as fast")
