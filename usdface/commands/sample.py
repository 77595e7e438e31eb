"""``usdface sample OUTDIR``: generate the procedural sample avatar, capture and ground truth."""

from __future__ import annotations

from . import json_path
from .options import add_quiet, nonnegative_float, nonnegative_int


def register(subparsers) -> None:
    parser = subparsers.add_parser(
        "sample", help="generate the sample avatar + capture + truth (deterministic)",
        description="Write a procedural UsdSkel head avatar (cm, Y up, 52 ARKit shapes), a capture of a "
                    "'person' on an ARKit-like face mask (capture.usda, metres; with --folder also as a "
                    "capture folder) and the ground truth (truth/*.npz). The same seed gives the same bytes "
                    "(see docs/sample-assets.md).")
    parser.add_argument("outdir", help="output folder (e.g. sample_assets)")
    parser.add_argument("--seed", type=nonnegative_int, default=0,
                        help="random seed, a whole number >= 0 (default 0: the committed assets)")
    parser.add_argument("--force", action="store_true",
                        help="write into an existing, non-empty folder: replace the files 'sample' writes, "
                             "keep every other file")
    parser.add_argument("--folder", action="store_true",
                        help="also write the capture as a capture folder OUTDIR/capture/ (OBJ + JSON, ~9 MB; "
                             "not part of the committed sample_assets/)")
    parser.add_argument("--take", action="store_true",
                        help="also write OUTDIR/take.usdc: a continuous take of the same person with its "
                             "meshes (every ARKit shape swept once, 30 fps, ~75 s, ~35 MB), to try "
                             "docs/takes.md ('capture select', 'fit TAKE', 'personalize AVATAR TAKE')")
    parser.add_argument("--template", choices=("generic", "artist"), default="generic",
                        help="the capture's template rig: the avatar's own generic shapes (default, the "
                             "committed sample) or another artist's rig, further from the person than the "
                             "avatar's shapes, as real phone apps ship (the bench's dev3 regime)")
    parser.add_argument("--scan-noise", type=nonnegative_float, metavar="MM", default=None,
                        help="the frames' scan noise, mm per coordinate (default 0.1; dev2's regime ~0.15)")
    parser.add_argument("--weight-noise", type=nonnegative_float, metavar="STD", default=None,
                        help="the phone weights' noise (default 0.01; dev2's scan regime ~0.03)")
    parser.add_argument("--picture", metavar="PNG", help="also draw the avatar and capture into this PNG")
    parser.add_argument("--json", action="store_true", help="print what was written as JSON")
    add_quiet(parser)
    parser.set_defaults(func=run)


def run(args) -> int:
    import json
    from pathlib import Path

    from ..io.atomic import check_output_file
    from ..sample import generate_samples

    if args.picture:  # checked before the folder is written
        check_output_file(args.picture, args.force, suffixes=(".png",), what="picture")
    noise = {"scan_noise_m": None if args.scan_noise is None else args.scan_noise * 1e-3,
             "weight_noise": args.weight_noise}
    from ..io.atomic import outputs_all_or_nothing

    done: dict = {}
    # the folder and the picture all or nothing, as export's outputs: a picture that failed (a full disk,
    # Ctrl-C) left a new sample folder behind as if the run had finished
    with outputs_all_or_nothing(done, folder=args.outdir, picture=args.picture):
        out = generate_samples(args.outdir, seed=args.seed, force=args.force, folder=args.folder,
                               template=args.template, take=args.take, **noise)
        done["folder"] = Path(out)
        picture = None
        if args.picture:
            from ..sample import build_samples
            from ..sample.picture import render_sample_picture, sample_title

            data = build_samples(args.seed, args.template, **noise)
            cap = data["capture"]
            picture = render_sample_picture(data["rigs"], cap.neutral, cap.triangles, args.picture,
                                            force=args.force, title=sample_title(data["meta"]))
            done["picture"] = Path(picture)
    meta = json.loads((Path(out) / "truth" / "meta.json").read_text())
    # what this run wrote (a --force run over an older folder keeps files it does not write: not counted)
    written = [Path(out) / n for n in ("README.txt", "avatar.usda", "capture.usda", "truth")]
    written += [Path(out) / "capture"] if args.folder else []
    written += [Path(out) / "take.usdc"] if args.take else []
    size = sum(f.stat().st_size for w in written for f in ([w] if w.is_file() else w.rglob("*"))
               if f.is_file())
    if args.json:
        print(json.dumps({"ok": True, "output": json_path(out), "bytes": size, "meta": meta,
                          "picture": str(picture) if picture else None}, default=str))
        return 0
    print(f"wrote {out}: avatar {meta['avatar_vertices']} vertices ({', '.join(meta['avatar_meshes'])}), "
          f"{meta['shapes']} shapes; capture {meta['capture_vertices']} vertices, "
          f"{meta['train_frames']} train + {meta['test_frames']} test frames"
          f"{'; a take (take.usdc)' if args.take else ''}; {size / 1e6:.1f} MB")
    if picture:
        print(f"wrote {picture}")
    return 0
